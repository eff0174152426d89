"""CDC-GS complexity: per-image high-frequency maps and the per-Gaussian complexity Gamma.

Maps (CDC-GS.md section 1): luma Y = 0.299 R + 0.587 G + 0.114 B at training resolution; one level
of the 2-D Haar DWT (ptwt), LL band zeroed, inverse DWT, absolute value, min-max normalised to
[0, 1]; or two levels (only the coarsest LL zeroed); or Sobel, Scharr, Laplacian magnitudes
(kornia) for the ablation. Kept as uint8 (x 255) on the training device.

Gamma (section 2): per view, the max over the pixels a Gaussian composites of
HF(p) * w_i(p) / w_max(p), computed by ``complexity_kernel`` (exact atomic max, or the CDC-GS
code's racy one emulated for diagnosis), with w_max(p) the largest alpha over the pixel's tile
list as the CDC-GS code has it, or the largest alpha * T as the paper's formula; across views the
max (or the mean over the views that see it). :func:`complexity_over_views` is the one place that
aggregates over views: the CDC-GS strategy, the viewer and the benchmarks call it.
"""

from __future__ import annotations

import kornia
import ptwt
import torch
import warp as wp

from ._interop import launch, small_table, warp_scope, wp_arg
from .kernels._constants import BLOCK_SIZE
from .kernels.blend import (
    MAX_EXACT,
    MAX_RACY_KEEP,
    MAX_RACY_RANK,
    VIEW_TABLE_COLUMNS,
    W_MAX_ALPHA,
    W_MAX_WEIGHT,
    complexity_kernel,
    complexity_views_kernel,
    w_max_alpha_kernel,
)
from .render import overflowed_renders

__all__ = [
    "AGGREGATIONS",
    "METHODS",
    "W_MAX_RULES",
    "ComplexityMaps",
    "ViewComplexity",
    "complexity_map",
    "complexity_over_views",
    "gaussian_complexity",
    "gaussian_complexity_views",
    "high_frequency",
    "luma",
]

METHODS = ("dwt", "dwt2", "sobel", "scharr", "laplacian")
AGGREGATIONS = ("max", "mean")
W_MAX_RULES = ("alpha", "weight")
# How the complexity pass finds w_max under the "alpha" rule: "walk", the complexity kernel's first
# pass (each pixel walks its tile's whole list), or "scatter", w_max_alpha_kernel before it (each
# list entry evaluated only at the pixels of its support box). The same values; on an H200 the
# scatter took 2.47 ms a view at 1M trained Gaussians against the walk's 1.98 (docs/benchmarks.md).
W_MAX_PASSES = ("walk", "scatter")
W_MAX_PASS = "walk"
# A Γ pass measures up to this many views in one launch (complexity_views_kernel) where it takes
# the exact max over pixels and views with the walk's w_max (the default): one view's launch
# leaves most SMs idle while its longest tile lists finish, and the next views' tiles take them.
# Their projections and tile lists are alive together: fewer views where they would hold more
# than GAMMA_VIEWS_BYTES. 1: one view a launch.
GAMMA_VIEWS_PER_LAUNCH = 8
GAMMA_VIEWS_BYTES = 1 << 30
LUMA = (0.299, 0.587, 0.114)


def luma(image: torch.Tensor) -> torch.Tensor:
    """[H, W] luma in [0, 1] of an [H, W, 3] uint8 or float image (proper RGB weights)."""
    rgb = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    return rgb @ rgb.new_tensor(LUMA)


def _normalise(x: torch.Tensor) -> torch.Tensor:
    """Min-max to [0, 1]; a response below 1e-6 (luma units) is rounding noise of a flat image."""
    lo, hi = x.min(), x.max()
    return (x - lo) / (hi - lo) if hi - lo > 1e-6 else torch.zeros_like(x)


def high_frequency(y: torch.Tensor, method: str = "dwt") -> torch.Tensor:
    """[H, W] high-frequency magnitude in [0, 1] of a luma image [H, W] (min-max normalised)."""
    h, w = y.shape
    if method in ("dwt", "dwt2"):
        level = 1 if method == "dwt" else 2
        coeffs = list(ptwt.wavedec2(y[None].double(), "haar", level=level))
        coeffs[0] = torch.zeros_like(coeffs[0])  # the coarsest approximation (LL) only
        detail = ptwt.waverec2(tuple(coeffs), "haar")[0, :h, :w]  # crop the padding back
        return _normalise(detail.abs()).float()
    image = y[None, None]
    if method == "sobel":
        response = kornia.filters.sobel(image, normalized=True)
    elif method == "scharr":
        kernel = y.new_tensor([[3.0, 0.0, -3.0], [10.0, 0.0, -10.0], [3.0, 0.0, -3.0]]) / 32.0
        gx = kornia.filters.filter2d(image, kernel[None], border_type="replicate")
        gy = kornia.filters.filter2d(image, kernel.T[None], border_type="replicate")
        response = torch.sqrt(gx * gx + gy * gy)
    elif method == "laplacian":
        response = kornia.filters.laplacian(image, kernel_size=3).abs()
    else:
        raise ValueError(f"complexity method must be one of {', '.join(METHODS)}, got {method!r}")
    return _normalise(response[0, 0])


def complexity_map(image: torch.Tensor, method: str = "dwt") -> torch.Tensor:
    """[H, W] uint8 complexity map (HF x 255) of an [H, W, 3] image, on the image's device."""
    return (high_frequency(luma(image), method) * 255.0 + 0.5).to(torch.uint8)


def gaussian_complexity(
    info,
    hf_map: torch.Tensor,
    opacities: torch.Tensor | None = None,
    *,
    w_max: str = "alpha",
    racy_seed: int | None = None,
    sums: bool = True,
    max_into: torch.Tensor | None = None,
    w_max_pass: str | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """(max [N], sum [N], count [N] int32) over one render's pixels of HF * w / w_max per Gaussian.

    ``info`` is the RasterizeInfo of the render; ``hf_map`` its view's [H, W] uint8 map.
    ``w_max`` (:data:`W_MAX_RULES`): "alpha", the largest alpha over the pixel's tile list (the
    CDC-GS code), or "weight", the largest alpha * T (the paper's formula). ``racy_seed``: emulate
    the CDC-GS code's racy per-Gaussian max (one pseudo-random contributing pixel per tile and
    Gaussian instead of the largest; the seed picks which) for the max; None: exact.
    Gaussians that composite no pixel get max 0 and count 0. ``sums`` False: the max alone (sum
    and count are None), for the max aggregations, which do not need the kernel's sums.
    ``max_into``: a float32 [N] tensor of non-negative values (a running max over earlier views)
    that the max is taken into, in place, and returned as the max (no zeroed array, no second
    pass to combine them). ``w_max_pass`` (:data:`W_MAX_PASSES`, None: :data:`W_MAX_PASS`): how
    the "alpha" rule's w_max is found; the same values either way.
    """
    if hf_map.shape != (info.height, info.width) or hf_map.dtype != torch.uint8:
        raise ValueError(
            f"hf_map must be a uint8 [{info.height}, {info.width}] map, got {hf_map.dtype} {list(hf_map.shape)}"
        )
    if w_max not in W_MAX_RULES:
        raise ValueError(f"w_max must be one of {', '.join(W_MAX_RULES)}, got {w_max!r}")
    w_max_pass = W_MAX_PASS if w_max_pass is None else w_max_pass
    if w_max_pass not in W_MAX_PASSES:
        raise ValueError(f"w_max_pass must be one of {', '.join(W_MAX_PASSES)}, got {w_max_pass!r}")
    scatter = w_max == "alpha" and w_max_pass == "scatter"
    n = info.means2d.shape[0]
    device = info.means2d.device
    opacities = info.opacities if opacities is None else opacities
    if max_into is None:
        max_out = torch.zeros(n, device=device)
    elif max_into.shape != (n,) or max_into.dtype != torch.float32 or max_into.device != device:
        raise ValueError(
            f"max_into must be a float32 [{n}] tensor on {device}, got {max_into.dtype} {list(max_into.shape)}"
        )
    else:
        max_out = max_into
    sum_out = torch.zeros(n if sums else 1, device=device)
    count_out = torch.zeros(n if sums else 1, dtype=torch.int32, device=device)
    racy = racy_seed is not None
    keys = torch.full((info.sorted_gauss_ids.numel() if racy else 1,), -1, dtype=torch.int32, device=device)
    tiles_y, tiles_x = info.tiles_y, info.tiles_x
    # Held here for the launches: a launch argument (a cached descriptor) does not keep its tensor alive.
    tensors = [
        info.tile_ranges,
        info.sorted_gauss_ids,
        info.means2d.detach().contiguous(),
        info.conics.detach().contiguous(),
        opacities.detach().contiguous(),
        hf_map.to(device).contiguous(),
        # every pixel's w_max, found before the complexity kernel (scatter), or nothing
        torch.full((info.height * info.width if scatter else 0,), 1.0e-4, device=device),
    ]
    with warp_scope(device):
        args = [
            wp_arg(t, dtype)
            for t, dtype in zip(tensors, (wp.int32, wp.int32, wp.vec2, wp.vec3, wp.float32, wp.uint8, wp.float32))
        ]
        if scatter:
            launch(
                w_max_alpha_kernel,
                tiles_x * tiles_y * BLOCK_SIZE,
                inputs=[*args[:5], info.width, info.height, tiles_x],
                outputs=[args[6]],
                block_dim=BLOCK_SIZE,
            )
        inputs = [
            *args[:6],
            info.width,
            info.height,
            tiles_x,
            W_MAX_ALPHA if w_max == "alpha" else W_MAX_WEIGHT,
            args[6],
        ]
        outputs = [wp_arg(max_out, wp.float32), wp_arg(sum_out, wp.float32), wp_arg(count_out, wp.int32)]
        seed = 0 if racy_seed is None else int(racy_seed) % (2**23)
        passes = (MAX_RACY_RANK, MAX_RACY_KEEP) if racy else (MAX_EXACT,)
        for max_rule in passes:
            launch(
                complexity_kernel,
                tiles_x * tiles_y * BLOCK_SIZE,
                inputs=[*inputs, max_rule, seed, int(sums), wp_arg(keys, wp.int32)],
                outputs=outputs,
                block_dim=BLOCK_SIZE,
            )
    return (max_out, sum_out, count_out) if sums else (max_out, None, None)


def gaussian_complexity_views(infos: list, hf_maps: list[torch.Tensor], max_into: torch.Tensor, w_max: str = "alpha"):
    """The max over pixels of :func:`gaussian_complexity` (``sums=False``, exact, w_max found by the
    walk) of several views of the same Gaussians and image size, taken into ``max_into`` in one
    launch: ``max_into`` ends as the max of itself and every view's, the same bits as one call of
    :func:`gaussian_complexity` per view with ``max_into`` (a max does not depend on the order).
    ``infos``: their :class:`cdcgs.render.RasterizeInfo` (binned; a render's or ``bin_view``'s),
    ``hf_maps`` their views' [H, W] uint8 maps. Returns ``max_into``. A view binned into slots
    whose pairs overflowed them (its ``pending`` overflow flag, read on the device) adds nothing:
    its lists are incomplete, and the caller measures it again from counted lists
    (:func:`complexity_over_views` does)."""
    if not infos or len(infos) != len(hf_maps):
        raise ValueError(
            f"gaussian_complexity_views needs as many maps as views (at least one), got {len(infos)} and {len(hf_maps)}"
        )
    if w_max not in W_MAX_RULES:
        raise ValueError(f"w_max must be one of {', '.join(W_MAX_RULES)}, got {w_max!r}")
    first = infos[0]
    n, width, height = first.means2d.shape[0], first.width, first.height
    device = first.means2d.device
    if max_into.shape != (n,) or max_into.dtype != torch.float32 or max_into.device != device:
        raise ValueError(
            f"max_into must be a float32 [{n}] tensor on {device}, "
            f"got {max_into.dtype} {list(max_into.shape)} on {max_into.device}"
        )
    maps = []
    for info, hf_map in zip(infos, hf_maps):
        if (info.width, info.height, info.means2d.shape[0], info.means2d.device) != (width, height, n, device):
            raise ValueError(
                f"gaussian_complexity_views measures views of one image size and the same Gaussians on one "
                f"device: a {info.width} x {info.height} view of {info.means2d.shape[0]} on {info.means2d.device} "
                f"beside a {width} x {height} one of {n} on {device}"
            )
        if hf_map.shape != (height, width) or hf_map.dtype != torch.uint8:
            raise ValueError(f"hf_map must be a uint8 [{height}, {width}] map, got {hf_map.dtype} {list(hf_map.shape)}")
        maps.append(hf_map.to(device).contiguous())
    rows, held = views_table_rows(infos, maps)
    table = small_table(device, rows, torch.int64)
    held.append(table)
    launch_complexity_views(table, first, w_max, max_into)
    return max_into


def views_table_rows(infos: list, hf_maps: list[torch.Tensor] | None) -> tuple[list[list[int]], list[torch.Tensor]]:
    """The rows of ``complexity_views_kernel``'s table for ``infos`` (checked by
    :func:`gaussian_complexity_views`), with their maps' addresses (0 without ``hf_maps``: the
    caller fills that column), and the tensors whose addresses they hold, to keep alive until the
    launch is queued."""
    held, rows = [], []
    for position, info in enumerate(infos):
        tensors = [
            info.tile_ranges.contiguous(),
            info.sorted_gauss_ids.contiguous(),
            info.means2d.detach().contiguous(),
            info.conics.detach().contiguous(),
            info.opacities.detach().contiguous(),
        ]
        held += tensors
        address = 0
        if hf_maps is not None:
            held.append(hf_maps[position])
            address = hf_maps[position].data_ptr()
        pending = getattr(info, "pending", None)  # [flags..., overflow, count] of lists binned into slots
        overflow = [0, 0] if pending is None else [pending.data_ptr(), pending.numel() - 2]
        rows.append([t.data_ptr() for t in tensors] + [address, tensors[1].numel(), *overflow])
    assert all(len(row) == VIEW_TABLE_COLUMNS for row in rows)
    return rows, held


def launch_complexity_views(table: torch.Tensor, like, w_max: str, max_into: torch.Tensor) -> None:
    """One launch of ``complexity_views_kernel`` over the views of ``table`` (int64
    [V, VIEW_TABLE_COLUMNS] on the device), views of the image size and Gaussians of the info
    ``like``, their maxima into ``max_into``."""
    device = max_into.device
    tiles_x, tiles_y = like.tiles_x, like.tiles_y
    # the kernel's unused arguments: no w_max map, no racy keys, no sums or counts
    unused = [torch.zeros(size, dtype=dtype, device=device) for size, dtype in _UNUSED_VIEWS_ARGUMENTS]
    with warp_scope(device):
        launch(
            complexity_views_kernel,
            table.shape[0] * tiles_x * tiles_y * BLOCK_SIZE,
            inputs=[
                wp_arg(table, wp.int64),
                like.means2d.shape[0],
                like.width,
                like.height,
                tiles_x,
                tiles_y,
                W_MAX_ALPHA if w_max == "alpha" else W_MAX_WEIGHT,
                wp_arg(unused[0], wp.float32),
                wp_arg(unused[1], wp.int32),
            ],
            outputs=[wp_arg(max_into, wp.float32), wp_arg(unused[2], wp.float32), wp_arg(unused[3], wp.int32)],
            block_dim=BLOCK_SIZE,
        )


# (size, dtype) of complexity_views_kernel's unused arrays: w_max map, keys, sums, counts
_UNUSED_VIEWS_ARGUMENTS = ((0, torch.float32), (0, torch.int32), (1, torch.float32), (1, torch.int32))


def views_per_launch(info) -> int:
    """How many views like ``info`` a Γ pass measures in one launch (:func:`views_per_launch_for`)."""
    return views_per_launch_for(info.means2d.shape[0], info.sorted_gauss_ids.numel())


def views_per_launch_for(gaussians: int, slots: int) -> int:
    """How many views of ``gaussians`` Gaussians and ``slots`` list entries each a Γ pass measures
    in one launch: :data:`GAMMA_VIEWS_PER_LAUNCH`, fewer where what they hold together (their
    projections, about 40 bytes a Gaussian, and tile lists, about 8 bytes an entry) would pass
    :data:`GAMMA_VIEWS_BYTES`."""
    return max(1, min(GAMMA_VIEWS_PER_LAUNCH, GAMMA_VIEWS_BYTES // max(40 * gaussians + 8 * slots, 1)))


class ComplexityMaps:
    """The complexity maps of a list of views, computed on first use and kept (a cache owned by
    whoever owns it: a training run, a viewer). Views whose image is not loaded yet are loaded.

    ``maps[i]`` is the [H, W] uint8 map of ``views[i]`` on ``device``.
    """

    def __init__(self, views, method: str = "dwt", device="cpu"):
        if method not in METHODS:
            raise ValueError(f"complexity method must be one of {', '.join(METHODS)}, got {method!r}")
        self.views = list(views)
        self.method = method
        self.device = torch.device(device)
        self._maps: list[torch.Tensor] | None = None

    @property
    def computed(self) -> bool:
        return self._maps is not None

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, index: int) -> torch.Tensor:
        return self.all()[index]

    def all(self) -> list[torch.Tensor]:
        if self._maps is None:
            from .io.views import load_images

            missing = [view for view in self.views if view.image is None]
            if missing:
                load_images(missing, device=self.device, progress=False)
            self._maps = [complexity_map(view.image.to(self.device), self.method) for view in self.views]
        return self._maps


class ViewComplexity:
    """Γ [N] of every Gaussian aggregated over views, one render at a time.

    ``pixel_aggregation`` within a view: the max over its pixels of HF w / w_max, or their mean;
    ``view_aggregation`` across views: the max, or the mean over the views that see the Gaussian;
    ``w_max`` and ``racy_max``: as :func:`gaussian_complexity` (the racy emulation draws a new
    pixel choice for each view added, the first with ``racy_seed``).
    """

    def __init__(
        self,
        num_gaussians: int,
        device,
        *,
        pixel_aggregation: str = "max",
        view_aggregation: str = "max",
        w_max: str = "alpha",
        racy_max: bool = False,
        racy_seed: int = 0,
    ):
        for name, value in (("pixel_aggregation", pixel_aggregation), ("view_aggregation", view_aggregation)):
            if value not in AGGREGATIONS:
                raise ValueError(f"{name} must be one of {', '.join(AGGREGATIONS)}, got {value!r}")
        if w_max not in W_MAX_RULES:
            raise ValueError(f"w_max must be one of {', '.join(W_MAX_RULES)}, got {w_max!r}")
        self.pixel_aggregation = pixel_aggregation
        self.view_aggregation = view_aggregation
        self.w_max = w_max
        self.racy_max = racy_max
        self.views_added = racy_seed  # the racy emulation's seed of the next view
        self.total = torch.zeros(num_gaussians, device=device)
        self.views_seen = torch.zeros(num_gaussians, device=device)

    @classmethod
    def from_state(cls, total: torch.Tensor, views_seen: torch.Tensor, **options) -> ViewComplexity:
        """An accumulator over existing [N] tensors (updated in place), e.g. a strategy's state."""
        accumulator = cls(0, total.device, **options)
        accumulator.total, accumulator.views_seen = total, views_seen
        return accumulator

    def add(self, info, hf_map: torch.Tensor) -> None:
        """Add one render (its RasterizeInfo) of a view with complexity map ``hf_map``."""
        racy_seed = self.views_added if self.racy_max else None
        sums = self.pixel_aggregation == "mean" or self.view_aggregation == "mean"
        if not sums:  # max over pixels and views: the kernel takes the max into the running one
            gaussian_complexity(info, hf_map, w_max=self.w_max, racy_seed=racy_seed, sums=False, max_into=self.total)
            self.views_added += 1
            return
        max_out, sum_out, count = gaussian_complexity(info, hf_map, w_max=self.w_max, racy_seed=racy_seed, sums=sums)
        self.views_added += 1
        per_view = max_out if self.pixel_aggregation == "max" else sum_out / count.clamp_min(1)
        if self.view_aggregation == "max":
            torch.maximum(self.total, per_view, out=self.total)
        else:
            self.total += per_view
            self.views_seen += (count > 0).float()

    def result(self) -> torch.Tensor:
        """[N] Γ; 0 for a Gaussian that no view saw."""
        return self.total if self.view_aggregation == "max" else self.total / self.views_seen.clamp_min(1)


@torch.no_grad()
def complexity_over_views(
    bins, maps: ComplexityMaps, num_gaussians: int, device, ranks=None, groups=None, **options
) -> torch.Tensor:
    """[N] Γ over every view of ``maps``: ``bins(i)`` is the :class:`cdcgs.render.RasterizeInfo`
    of view ``i``'s projection and tile lists (:func:`cdcgs.render.bin_view`, which skips the
    colours and the blend that Γ does not read, or a render's info), or a
    :class:`cdcgs.render.PendingBins` that gives it (:func:`cdcgs.render.start_bin_view`). With
    pending bins the next view is started before this one is finished and measured, so that the
    GPU projects and counts it while the host waits for this one's intersection count; with
    finished ones, one view at a time. Under the exact max the views measured in one launch
    (:func:`views_per_launch`) are alive together, with the next one's projection. The same Γ
    either way.

    An info binned into slots (``bin_view(..., capacity=...)``, its ``pending`` flags set) reads
    nothing back: the flags of all such views are read once, after the last view. A view whose
    pairs overflowed its slots has incomplete lists: under the exact max over pixels and views (the
    default, with the walk's w_max) it added nothing, and it alone is measured again from
    ``bins(i, counted=True)``, which reads its count; under the other aggregations its values are
    in the sums already, and the whole pass is taken again from counted lists. An input that held
    NaN or inf raises NonFiniteError, as a counted view does at once.

    ``groups``: an object whose ``measure(indices, maps, total, w_max)`` measures the views
    ``indices`` under the exact max into ``total`` itself (binned into slots, a launch's worth of
    views at a time: :class:`cdcgs.train.graph.GammaGroups` replays one CUDA graph for them) and
    returns their (index, ``pending_flags``), or None when it cannot (then ``bins`` is used), and
    whose ``release()`` lets go of what it holds; used under the exact max only.

    ``options``: ``pixel_aggregation``, ``view_aggregation``, ``w_max``, ``racy_max`` and
    ``racy_seed`` of :class:`ViewComplexity`. ``ranks`` (a :class:`cdcgs.train.distributed.Ranks`
    of several processes): each bins the views ``rank``, ``rank + world``, ... and the
    processes' sums or maxima are reduced, so every process gets the Γ of all views.
    """
    rank, world = (ranks.rank, ranks.world) if ranks is not None else (0, 1)
    indices = list(range(rank, len(maps), world))
    accumulator = ViewComplexity(num_gaussians, device, **options)
    try:
        slotted = None
        if groups is not None and indices and _together(accumulator):
            slotted = groups.measure(indices, maps, accumulator.total, accumulator.w_max)
        if slotted is None:  # view by view
            _, slotted = _measure_views(bins, maps, indices, num_gaussians, device, options, accumulator)
        overflowed = overflowed_renders([flags for _, flags in slotted]) if slotted else []  # one read
    finally:
        if groups is not None:
            groups.release()  # after the read of its flags, which its memory holds

    def counted(index: int):
        return bins(index, counted=True)

    if overflowed and _together(accumulator):  # the views that overflowed added nothing: they alone again
        again = [slotted[position][0] for position in overflowed]
        _measure_views(counted, maps, again, num_gaussians, device, options, accumulator)
    elif overflowed:  # their incomplete lists are in the sums: the whole pass again
        accumulator, _ = _measure_views(counted, maps, indices, num_gaussians, device, options)
    if world > 1:
        if accumulator.view_aggregation == "max":
            ranks.all_reduce_(accumulator.total, "max")
        else:
            ranks.all_reduce_(accumulator.total)
            ranks.all_reduce_(accumulator.views_seen)
    return accumulator.result()


def _together(accumulator: ViewComplexity) -> bool:
    """Whether a pass into ``accumulator`` measures its views with :func:`gaussian_complexity_views`:
    the exact max over pixels and views, with the walk's w_max."""
    return (
        accumulator.pixel_aggregation == "max"
        and accumulator.view_aggregation == "max"
        and not accumulator.racy_max
        and (accumulator.w_max == "weight" or W_MAX_PASS == "walk")
    )


def _measure_views(bins, maps, indices, num_gaussians, device, options, accumulator=None):
    """(the accumulator of ``indices``' views, (index, ``pending_flags``) of those binned into
    slots). Where the accumulator takes the exact max over pixels and views with the walk's w_max
    (:func:`_together`), the views are measured up to :func:`views_per_launch` at a time
    (:func:`gaussian_complexity_views`, where a view whose slots overflowed adds nothing), else one
    at a time; the same Γ either way. ``accumulator``: add to this one instead of a new one."""
    accumulator = accumulator or ViewComplexity(num_gaussians, device, **options)
    seed = accumulator.views_added
    slotted = []
    together = _together(accumulator)
    waiting = []  # (index, info) of the views measured together next

    def measure_waiting() -> None:
        if waiting:
            infos = [info for _, info in waiting]
            maps_of = [maps[index] for index, _ in waiting]
            gaussian_complexity_views(infos, maps_of, accumulator.total, accumulator.w_max)
        waiting.clear()

    def started(position: int):
        return bins(indices[position]) if position < len(indices) else None

    current = started(0)
    for position, index in enumerate(indices):
        pending = hasattr(current, "finish")
        following = started(position + 1) if pending else None  # queued before this view's count is read
        info = current.finish() if pending else current
        if getattr(info, "pending", None) is not None:
            slotted.append((index, info.pending_flags))
        # the racy emulation's draw of this view, wherever it runs (unused by the exact max)
        accumulator.views_added = seed + index
        if together:
            if waiting and (info.width, info.height) != (waiting[0][1].width, waiting[0][1].height):
                measure_waiting()  # one launch takes views of one size
            waiting.append((index, info))
            if len(waiting) >= views_per_launch(info):
                measure_waiting()
        else:
            accumulator.add(info, maps[index])
        current = following if pending else started(position + 1)
    measure_waiting()
    return accumulator, slotted
