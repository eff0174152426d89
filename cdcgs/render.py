"""The torch face of the rasterizer: validation, zero-copy sharing with Warp, autograd.

``rasterize`` is the one public entry point. Tensors stay on their device; Warp reads and writes
torch's memory directly (``wp.from_torch``) on torch's current CUDA stream. A camera is checked on
every call, unless it comes as a :class:`PreparedCamera` (:func:`prepare_camera`), checked and built
once by whoever renders the same view again and again.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp
from torch.autograd.graph import increment_version

from ._interop import halt_arg as _halt_arg
from ._interop import launch as _launch
from ._interop import torch_allocators as _torch_allocators
from ._interop import torch_tensor as _torch
from ._interop import warp_scope as _warp_scope
from ._interop import wp_arg as _arg
from ._interop import wp_array as _wp
from .errors import CapacityError, NonFiniteError, PeerError
from .kernels._checks import find_nonfinite_kernel
from .kernels._constants import BLOCK_SIZE, MAX_SH_COEFFICIENTS, MAX_SH_DEGREE, TILE_SIZE
from .kernels._statistics import accumulate_statistics_kernel
from .kernels.adam import AdamStep
from .kernels.binning import BinningStart, TileBins, finish_binning, finish_binning_within, start_binning
from .kernels.blend import (
    blend_backward_kernel,
    blend_backward_lean_kernel,
    blend_backward_lean_warp_kernel,
    blend_backward_warp_kernel,
    blend_forward_chunked_kernel,
    blend_forward_kernel,
    walk_chunks_kernel,
)
from .kernels.projection import (
    SH_BLOCK,
    Camera,
    make_camera,
    project_gaussians_kernel,
    sh_to_color_backward_kernel,
    sh_to_color_grouped_backward_kernel,
    sh_to_color_kernel,
    sh_to_color_staged_backward_kernel,
)

__all__ = [
    "PendingBins",
    "PreparedCamera",
    "RasterizeInfo",
    "ShAdamStep",
    "any_overflowed",
    "bin_view",
    "overflowed_renders",
    "prepare_camera",
    "rasterize",
    "sh_adjoint",
    "start_bin_view",
]

# The SH adjoint's kernel on CUDA: "staged" (the coefficients in shared memory, one thread per
# Gaussian; the default) or "grouped" (16 threads per Gaussian, half-warp shuffles). On an H100
# (2026-11-26, benchmarks/profile_step.py) staged took 0.151 ms at 1M Gaussians and 0.446 ms at 3M
# against grouped's 0.292 and 0.870; each Gaussian's gradient is written by one thread, without
# atomics, in both.
SH_BACKWARD_CUDA = "staged"

# How the blend adjoint adds each Gaussian's gradients on CUDA: "block" (the warps' sums meet in
# the block's shared memory, one global atomic per tile and Gaussian; the default) or "warp" (each
# warp adds its own sums to global memory). The CPU runs the same code for both.
BLEND_BACKWARD_CUDA = "block"

# The blend adjoint's work per block: 0, a tile's whole walk (from the last contributor of any of
# its pixels down to its list's start); or a multiple of BLOCK_SIZE, chunks of that many list
# entries, each its own block, starting from per-pixel checkpoints that the forward pass saves at
# the chunk boundaries (rows of 20 bytes a pixel, pairs / BLEND_CHUNK + tiles of them). A tile
# whose walk is ten times the mean holds the whole launch up (benchmarks/tile_balance.py);
# chunks spread it over the GPU. 256 by default: on an H100 the replayed step of a trained bonsai
# model took 0.85x its time with whole tiles, and a training 0.85x (docs/benchmarks.md). (With
# chunks the image is saved for the backward pass, so changing it in place before then is an
# autograd error.)
BLEND_CHUNK = 256

# The most slots ``rasterize(capacity=...)`` takes: the sort holds twice as many keys, and Warp's
# launches and sorts index with 32-bit integers.
MAX_CAPACITY = 2**30


@dataclass
class RasterizeInfo:
    """What a render knows besides the image. Per-Gaussian tensors are [N, ...] in input order.

    Attributes:
        width, height: image size in pixels; tile_size: tile side in pixels (``TILE_SIZE``, 16);
            tiles_x, tiles_y: tiles per row and per column.
        means2d: [N, 2] pixel coordinates of the projected means (0 for culled Gaussians). A node
            of the autograd graph: call ``means2d.retain_grad()`` before ``backward`` to read the
            screen-space positional gradient, or use :meth:`positional_gradient`.
        conics: [N, 3] inverse 2D covariance (a, b, c) of the dilated footprint, px^-2.
        depths: [N] camera-space z. opacities: [N] opacities as composited (after the
            anti-aliasing compensation when ``antialiased``). colors: [N, 3] composited colours
            (with ``sh``: 0 for culled Gaussians, whose colour is not evaluated).
        radii: [N, 2] int32 per-axis pixel radius of the footprint (0 = culled).
        visible: [N] bool, radii > 0 (in front of the near plane and overlapping the image).
        tile_counts: [N] int32 tiles touched; num_intersections: their sum.
        tile_ranges: [tiles_y * tiles_x, 2] int32 [start, end) into ``sorted_gauss_ids`` of each
            tile, row-major (tile ty * tiles_x + tx), as the kernels take it;
            ``tile_ranges.view(tiles_y, tiles_x, 2)`` indexes it by tile row and column.
        sorted_gauss_ids: [num_intersections] int32 Gaussian ids ordered by (tile, depth).
        last_contributor: [H, W] int32 index into ``sorted_gauss_ids`` of each pixel's last
            composited Gaussian (start - 1 when none).
        (From :func:`bin_view`, which does no blend: ``colors``, ``last_contributor``,
        ``transmittance`` and ``depth`` are None.)
        transmittance: [H, W] final transmittance (1 - alpha).
        depth: [H, W] expected depth (sum of weight x depth / alpha, 0 where alpha is 0) when
            ``render_depth`` was asked for, else None. Differentiable.
        means2d_absgrad: [N, 2] sum over pixels of |d loss / d means2d| per pixel (AbsGS), filled
            by the backward pass when :meth:`retain_absgrad` asked for it before; else None.
        pending: for a render with ``capacity``, what it did not read on the host: the [K + 2]
            int32 device tensor of the inputs' non-finite flags (a sharded render's also the flag
            of another process's wrong arguments), then whether the pairs overflowed the slots,
            then their count (:meth:`check` reads it); None otherwise, where the render
            read its count and checked its inputs itself. ``num_intersections`` is then the
            capacity, and ``sorted_gauss_ids`` ends with empty slots (-1) that belong to no tile.
    """

    width: int
    height: int
    tile_size: int
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    radii: torch.Tensor
    tile_counts: torch.Tensor
    num_intersections: int
    tile_ranges: torch.Tensor
    sorted_gauss_ids: torch.Tensor
    last_contributor: torch.Tensor
    transmittance: torch.Tensor
    depth: torch.Tensor | None
    _absgrad: dict = field(default_factory=dict, repr=False)  # shared with the blend's backward pass
    pending: torch.Tensor | None = None
    _pending_names: tuple = field(default=(), repr=False)
    _pending_stream: object = field(default=None, repr=False)  # the CUDA stream the render queued on
    # an error the render put off until check(): a sharded render's process with wrong arguments
    # (cdcgs.train.shards), which took its part in the exchanges instead of leaving the others waiting
    _deferred: Exception | None = field(default=None, repr=False)

    def check(self) -> int:
        """The view's number of (tile, Gaussian) pairs, read from the device (one synchronisation).

        For a render with ``capacity`` it also raises what that render did not: NonFiniteError
        naming an input that held NaN or inf, then CapacityError when the pairs overflowed the
        slots (the image and the gradients are then wrong). Without ``capacity``: the count, which
        the render read already. A sharded render with ``capacity``
        (:func:`cdcgs.train.shards.rasterize_shard`) raises first this process's own wrong
        argument, which it went on past with zeros, and PeerError for another process's; its
        CapacityError is this process's view's alone."""
        if self.pending is None:
            if self._deferred is not None:
                raise self._deferred
            return self.num_intersections
        stream = self._pending_stream
        with torch.cuda.stream(stream) if stream is not None else contextlib.nullcontext():
            values = self.pending.tolist()  # on the render's stream, after its work, whatever is current now
        if self._deferred is not None:  # raised after the read: the render's transfers are done by now
            raise self._deferred
        overflowed, count = _pending_outcome(self._pending_names, values)
        if overflowed:
            raise CapacityError(count, self.num_intersections)
        return count

    @property
    def pending_flags(self) -> tuple[torch.Tensor, tuple] | None:
        """(``pending``, the names of its finiteness flags) for :func:`any_overflowed`: what a
        render with ``capacity`` left on the device, without the rest of the info. None without.
        A sharded render's process whose own arguments were wrong has no flags to give: its error
        is raised here (call :meth:`check` for it after the backward pass)."""
        if self._deferred is not None:
            raise self._deferred
        return None if self.pending is None else (self.pending, self._pending_names)

    @property
    def tiles_x(self) -> int:
        """Tiles per image row: ceil(width / tile_size)."""
        return -(-self.width // self.tile_size)

    @property
    def tiles_y(self) -> int:
        """Tiles per image column: ceil(height / tile_size)."""
        return -(-self.height // self.tile_size)

    @property
    def visible(self) -> torch.Tensor:
        return (self.radii > 0).all(dim=-1)  # computed when asked: two launches a render saved

    @property
    def means2d_absgrad(self) -> torch.Tensor | None:
        return self._absgrad.get("sums")

    def retain_absgrad(self) -> torch.Tensor:
        """Ask the next ``backward`` to fill ``means2d_absgrad`` (AbsGS), like ``retain_grad()``; the
        backward pass skips these sums otherwise. Returns the [N, 2] tensor it will fill."""
        if "sums" not in self._absgrad:
            self._absgrad["sums"] = self.means2d.new_zeros(self.means2d.shape[0], 2)
        return self._absgrad["sums"]

    def _gradient(self, absolute: bool) -> torch.Tensor:
        """[N, 2] pixel-space positional gradient of the backward pass (AbsGS's sums with
        ``absolute``); RuntimeError when the render was not asked to keep it."""
        if absolute:
            grad = self.means2d_absgrad
            if grad is None:
                raise RuntimeError(
                    "call info.retain_absgrad() before backward() to read the absolute positional gradient"
                )
            return grad
        grad = self.means2d.grad
        if grad is None:
            raise RuntimeError("call info.means2d.retain_grad() before backward() to read the positional gradient")
        return grad

    def positional_gradient(self, absolute: bool = False) -> torch.Tensor:
        """[N] norm of the screen-space positional gradient of this view in NDC units (3DGS).

        The pixel-space gradient of ``means2d`` scaled by W/2 in x and H/2 in y, as 3DGS
        accumulates it for densification; ``absolute`` gives the AbsGS variant (sum of per-pixel
        absolute values). Valid after ``backward``; zero where no gradient reached.
        """
        grad = self._gradient(absolute)
        # Filled on the device: a tensor made from a host list is a blocking copy, and the host
        # would wait for the GPU at every view that accumulates statistics.
        scale = grad.new_empty(2)
        scale[0], scale[1] = 0.5 * self.width, 0.5 * self.height
        return (grad * scale).norm(dim=-1)

    def accumulate_statistics(
        self,
        grad_sum: torch.Tensor,
        count: torch.Tensor,
        max_radius: torch.Tensor,
        absolute: bool = False,
        halt: torch.Tensor | None = None,
    ) -> None:
        """Add this view's densification statistics in place, one launch: for every Gaussian it
        sees (both radii > 0) :meth:`positional_gradient` (``absolute``: AbsGS's) to ``grad_sum``,
        1 to ``count``, and its largest radius into ``max_radius`` (each [N] float32 on the
        render's device). Valid after ``backward``, as :meth:`positional_gradient`. ``halt``: an
        int32 device flag; while its first entry is non-zero nothing is added."""
        gradient = self._gradient(absolute)
        n = gradient.shape[0]
        for name, tensor in (("grad_sum", grad_sum), ("count", count), ("max_radius", max_radius)):
            if tensor.shape != (n,) or tensor.dtype != torch.float32 or tensor.device != gradient.device:
                raise ValueError(
                    f"{name} must be a float32 [{n}] tensor on {gradient.device}, got "
                    f"{tensor.dtype} {list(tensor.shape)} on {tensor.device}"
                )
            if not tensor.is_contiguous():
                raise ValueError(f"{name} must be contiguous (it is updated in place)")
        gradient = gradient.contiguous()  # held until the launch is queued
        with _warp_scope(gradient.device):
            _launch(
                accumulate_statistics_kernel,
                n,
                inputs=[
                    _arg(gradient, wp.vec2),
                    _arg(self.radii, wp.vec2i),
                    0.5 * self.width,
                    0.5 * self.height,
                ],
                outputs=[
                    _arg(grad_sum, wp.float32),
                    _arg(count, wp.float32),
                    _arg(max_radius, wp.float32),
                    _halt_arg(halt, gradient.device),
                ],
            )


# --------------------------------------------------------------------------------------------
# Autograd functions


def _project(means, quats, scales, opacities, camera: PreparedCamera, antialiased: bool, nonfinite):
    """(means2d, conics, depths, opacities as composited, radii) of every Gaussian; the flags of
    non-finite means, quats, scales and opacities go to ``nonfinite[0:4]``."""
    n = means.shape[0]
    # The kernel writes every entry (zeros for culled Gaussians): no zero fills.
    means2d = means.new_empty(n, 2)
    conics = means.new_empty(n, 3)
    depths = means.new_empty(n)
    out_opacities = means.new_empty(n)
    radii = torch.empty(n, 2, dtype=torch.int32, device=means.device)
    with _warp_scope(means.device):
        _launch(
            project_gaussians_kernel,
            n,
            inputs=_project_inputs(means, quats, scales, opacities, camera, antialiased),
            outputs=[*_project_outputs(means2d, conics, depths, out_opacities, radii), _arg(nonfinite, wp.int32)],
        )
    return means2d, conics, depths, out_opacities, radii


def _bin(means2d, radii, depths, conics, opacities, width: int, height: int, read_count) -> TileBins:
    """The depth-sorted tile lists of a projection, each Gaussian only in the tiles where it
    reaches alpha 1/255 (``read_count``: as :func:`cdcgs.kernels.binning.bin_gaussians`)."""
    start = _start_bin(means2d, radii, depths, conics, opacities, width, height)
    return finish_binning(start, int(read_count(start.offsets)))


def _start_bin(means2d, radii, depths, conics, opacities, width: int, height: int) -> BinningStart:
    """:func:`_bin`'s first half, up to the prefix sum of the tile counts (nothing read back)."""
    allocate, zeros = _torch_allocators(means2d.device)
    return start_binning(
        _wp(means2d.detach(), wp.vec2),
        _wp(radii, wp.vec2i),
        _wp(depths.detach(), wp.float32),
        width,
        height,
        allocate=allocate,
        zeros=zeros,
        conics=_wp(conics.detach(), wp.vec3),
        opacities=_wp(opacities.detach(), wp.float32),
        launch=_launch,
    )


def _count_reader(nonfinite: torch.Tensor, names):
    """``read_count`` for :func:`_bin`: the single host synchronisation of a render, where the
    intersection count sizes the sort buffers. The finiteness flags (``nonfinite[i]`` for
    ``names[i]``) travel with it, so that validation costs no extra synchronisation."""

    def read_count(offsets: wp.array) -> int:
        values = torch.cat([nonfinite, _torch(offsets)[-1:]]).tolist()
        _raise_nonfinite(names, values)
        return values[-1]

    return read_count


def any_overflowed(flags: list[tuple[torch.Tensor, tuple]]) -> bool:
    """The :attr:`RasterizeInfo.pending_flags` of several renders with ``capacity``, read in one
    synchronisation (on the current stream): NonFiniteError naming the first input that held NaN
    or inf, else whether any render's pairs overflowed its slots."""
    return bool(overflowed_renders(flags))


def overflowed_renders(flags: list[tuple[torch.Tensor, tuple]]) -> list[int]:
    """As :func:`any_overflowed`, read in one synchronisation: the positions in ``flags`` of the
    renders whose pairs overflowed their slots (after NonFiniteError for any that met NaN or inf)."""
    rows = torch.stack([pending for pending, _ in flags]).tolist()
    outcomes = [_pending_outcome(names, row) for row, (_, names) in zip(rows, flags)]  # every NaN first
    return [position for position, (overflowed, _) in enumerate(outcomes) if overflowed]


def _pending_outcome(names, values) -> tuple[bool, int]:
    """(overflowed, count) of one render's ``pending`` values, after NonFiniteError for a flagged input."""
    _raise_nonfinite(names, values)
    overflowed, count = values[-2:]
    return bool(overflowed), count


def _raise_nonfinite(names, flags) -> None:
    """NonFiniteError for the first of ``names`` whose flag (read from the device) is set
    (PeerError for a sharded render's flag of another process's wrong arguments)."""
    for name, bad in zip(names, flags):
        if bad:
            raise PeerError() if name == PeerError.FLAG else NonFiniteError(name)


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, camera: PreparedCamera, antialiased: bool, nonfinite):
        means2d, conics, depths, out_opacities, radii = _project(
            means, quats, scales, opacities, camera, antialiased, nonfinite
        )
        ctx.save_for_backward(means, quats, scales, opacities, means2d, conics, depths, out_opacities, radii)
        ctx.camera = camera
        ctx.antialiased = antialiased
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, out_opacities, radii

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_depths, grad_opacities_out, _grad_radii):
        means, quats, scales, opacities, means2d, conics, depths, out_opacities, radii = ctx.saved_tensors
        n = means.shape[0]
        # One zero fill for the four gradients the adjoint adds to: [means | quats | scales | opacities].
        grads_in = [
            part.view(t.shape)
            for part, t in zip(
                means.new_zeros(11 * n).split([3 * n, 4 * n, 3 * n, n]), (means, quats, scales, opacities)
            )
        ]
        grads_out = [
            _grad_or_zeros(g, t)
            for g, t in zip(
                (grad_means2d, grad_conics, grad_depths, grad_opacities_out), (means2d, conics, depths, out_opacities)
            )
        ]
        with _warp_scope(means.device):
            _launch(
                project_gaussians_kernel,
                means.shape[0],
                inputs=_project_inputs(means, quats, scales, opacities, ctx.camera, ctx.antialiased),
                outputs=[*_project_outputs(means2d, conics, depths, out_opacities, radii), None],
                adj_inputs=[*(_arg(g, t) for g, t in zip(grads_in, _PROJECT_INPUT_TYPES)), Camera(), None, 0],
                adj_outputs=[*_project_outputs(*grads_out, radii)[:4], None, None],
                adjoint=True,
            )
        return (*grads_in, None, None, None)


_PROJECT_INPUT_TYPES = (wp.vec3, wp.vec4, wp.vec3, wp.float32)


def _project_inputs(means, quats, scales, opacities, camera: PreparedCamera, antialiased):
    return [
        *(_arg(t, dtype) for t, dtype in zip((means, quats, scales, opacities), _PROJECT_INPUT_TYPES)),
        camera.camera,
        _on_device(camera, means.device),
        int(antialiased),
    ]


_NO_CAMERA: dict = {}  # device -> an empty Warp array of Camera (the kernels' "no camera on the device")


def _on_device(camera: PreparedCamera, device: torch.device):
    """The kernels' ``camera_on_device`` argument: the camera's device copy, or an empty array."""
    if camera.on_device is not None:
        return camera.on_device
    key = str(device)
    if key not in _NO_CAMERA:
        _NO_CAMERA[key] = wp.empty(0, dtype=Camera, device=wp.device_from_torch(device))
    return _NO_CAMERA[key]


def _project_outputs(means2d, conics, depths, opacities, radii):
    return [
        _arg(means2d, wp.vec2),
        _arg(conics, wp.vec3),
        _arg(depths, wp.float32),
        _arg(opacities, wp.float32),
        _arg(radii, wp.vec2i),
    ]


def _grad_or_zeros(grad: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    return torch.zeros_like(like) if grad is None else grad.contiguous()


class _ShColor(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, sh, sh_rest, sh_degree: int, camera: PreparedCamera, radii, nonfinite, sh_step):
        colors = means.new_empty(means.shape[0], 3)
        with _warp_scope(means.device):
            _launch(
                sh_to_color_kernel,
                means.shape[0],
                inputs=[
                    _arg(means, wp.vec3),
                    _arg(sh, wp.vec3),
                    None if sh_rest is None else _arg(sh_rest, wp.vec3),
                    sh_degree,
                    camera.center,
                    _on_device(camera, means.device),
                    _arg(radii, wp.vec2i),
                ],
                outputs=[_arg(colors, wp.vec3), _arg(nonfinite, wp.int32)],
            )
        ctx.save_for_backward(means, sh, sh_rest, radii, colors)
        ctx.sh_degree = sh_degree
        ctx.camera = camera
        ctx.sh_step = sh_step
        return colors

    @staticmethod
    def backward(ctx, grad_colors):
        means, sh, sh_rest, radii, colors = ctx.saved_tensors
        grad_means, grad_sh, grad_sh_rest = sh_adjoint(
            means, sh, sh_rest, ctx.sh_degree, ctx.camera, radii, colors, grad_colors, step=ctx.sh_step
        )
        return grad_means, grad_sh, grad_sh_rest, None, None, None, None, None


@dataclass(frozen=True)
class ShAdamStep:
    """One Adam step of the SH coefficients, which the render's adjoint applies in place of
    returning their gradients (``rasterize(sh_step=...)``): the SH adjoint writes each coefficient's
    gradient and Adam reads it back, about 0.4 GB a step at a million Gaussians of degree 3; with a
    step the kernel that computes a Gaussian's gradients updates its coefficients and moments at
    once. A replayed training step of one view uses it (:mod:`cdcgs.train.graph`); the update is
    ``cdcgs.kernels.adam.adam_value``'s, as FusedAdam's (on CUDA built with the SH kernels' fast
    math: division and square root to a few units in the last place).

    ``rates``: float32 [P, 8] on the render's device, rows as ``FusedAdam.advance`` gives them (read
    when the adjoint runs); ``rows``: the rows of ``sh``'s and ``sh_rest``'s rates; ``sh_moments``
    and ``rest_moments``: (exp_avg, exp_avg_sq) of ``sh`` and ``sh_rest``, float32, contiguous, of
    their shapes; ``halt``: an int32 device flag, the step changes nothing while its first entry is
    non-zero (None: never); ``selective``: step only the Gaussians the view sees (both radii
    positive, ``info.visible``), as ``FusedAdam.step(selected)`` with that mask. Only the render's
    own gradient reaches the coefficients: a loss that also reads them otherwise would lose the
    rest of their gradient."""

    rates: torch.Tensor
    rows: tuple[int, int]
    sh_moments: tuple[torch.Tensor, torch.Tensor]
    rest_moments: tuple[torch.Tensor, torch.Tensor]
    halt: torch.Tensor | None = None
    selective: bool = False


def _check_sh_step(step, sh, sh_rest, device: torch.device, given: tuple) -> None:
    """Refuse an ``sh_step`` that the adjoint could not apply, naming what is wrong (before any work).
    ``sh`` and ``sh_rest`` as checked, ``given`` as the caller passed them (a step updates those: a
    checked copy would take it instead)."""
    if step is None:
        return
    if not isinstance(step, ShAdamStep):
        raise ValueError(f"sh_step must be a ShAdamStep, got {type(step).__name__}")
    if sh is None or sh_rest is None:
        raise ValueError("sh_step updates sh ([N, 1, 3]) and sh_rest: pass both, not colors or sh alone")
    rates = step.rates
    if not (
        isinstance(rates, torch.Tensor)
        and rates.dtype == torch.float32
        and rates.dim() == 2
        and rates.shape[1] == 8
        and rates.device == device
        and rates.is_contiguous()
    ):
        got = f"{rates.dtype} {list(rates.shape)} on {rates.device}" if isinstance(rates, torch.Tensor) else rates
        raise ValueError(f"sh_step.rates must be a contiguous float32 [P, 8] tensor on {device}, got {got}")
    if len(step.rows) != 2 or not all(isinstance(r, int) and 0 <= r < rates.shape[0] for r in step.rows):
        raise ValueError(f"sh_step.rows must be two rows of its [{rates.shape[0]}, 8] rates, got {step.rows!r}")
    for name, param, original, moments in (
        ("sh", sh, given[0], step.sh_moments),
        ("sh_rest", sh_rest, given[1], step.rest_moments),
    ):
        if param is not original:
            raise ValueError(f"sh_step updates {name} in place, which must be a contiguous float32 tensor on {device}")
        for moment in moments:
            if not (
                isinstance(moment, torch.Tensor)
                and moment.shape == param.shape
                and moment.dtype == torch.float32
                and moment.device == device
                and moment.is_contiguous()
            ):
                got = (
                    f"{moment.dtype} {list(moment.shape)} on {moment.device}"
                    if isinstance(moment, torch.Tensor)
                    else moment
                )
                raise ValueError(
                    f"sh_step's moments of {name} must be contiguous float32 {list(param.shape)} tensors on {device}, got {got}"
                )
    _halt_arg(step.halt, device)  # raises for a bad flag


def _adam_steps(step: ShAdamStep | None, sh: torch.Tensor, sh_rest: torch.Tensor | None, radii) -> tuple:
    """The kernels' (dc_step, rest_step) arguments: ``step``'s as Warp structs, or two empty ones."""
    if step is None:
        return _NO_STEP, _NO_STEP
    rates = _wp(step.rates, wp.float32)
    halt = _wp(step.halt, wp.int32) if step.halt is not None else None
    visible = _wp(radii, wp.vec2i) if step.selective else None
    structs = []
    for param, (exp_avg, exp_avg_sq), row in zip((sh, sh_rest), (step.sh_moments, step.rest_moments), step.rows):
        struct = AdamStep()
        struct.param = _wp(param.view(-1), wp.float32)
        struct.exp_avg = _wp(exp_avg.view(-1), wp.float32)
        struct.exp_avg_sq = _wp(exp_avg_sq.view(-1), wp.float32)
        struct.rates, struct.row, struct.halt = rates, row, halt
        struct.radii, struct.row_width = visible, max(param[0].numel() if param.shape[0] else 1, 1)
        structs.append(struct)
    return tuple(structs)


_NO_STEP = AdamStep()  # empty: the kernels write the coefficients' gradients


def sh_adjoint(
    means,
    sh,
    sh_rest,
    sh_degree: int,
    camera: PreparedCamera,
    radii,
    colors,
    grad_colors,
    step: ShAdamStep | None = None,
):
    """The adjoint of the colours of one view (``colors`` = max(SH(direction from ``camera``), 0) of
    the Gaussians whose ``radii`` are positive): (grad means, grad ``sh``, grad ``sh_rest``) for the
    colours' gradient ``grad_colors`` [N, 3]. Every entry is written (culled Gaussians get 0). With
    ``step`` (a :class:`ShAdamStep`, checked by the caller) the coefficients' gradients go to its
    Adam update of ``sh`` and ``sh_rest`` instead, in the same kernel: (grad means, None, None)."""
    grad_means = torch.empty_like(means)
    grad_sh = torch.empty(0, 1, 3, device=means.device) if step is not None else torch.empty_like(sh)
    grad_sh_rest = None
    if sh_rest is not None:
        grad_sh_rest = (
            torch.empty(0, *sh_rest.shape[1:], device=means.device) if step is not None else torch.empty_like(sh_rest)
        )
    grad_colors = grad_colors.contiguous()  # held here: a launch argument does not keep its tensor alive
    cuda = means.device.type == "cuda"
    n = means.shape[0]
    staged = cuda and SH_BACKWARD_CUDA == "staged" and sh_rest is not None and sh_rest.shape[1] < MAX_SH_COEFFICIENTS
    if staged:  # shared memory, one thread per Gaussian; the higher coefficients as flat floats
        kernel, dim, block = sh_to_color_staged_backward_kernel, -(-n // SH_BLOCK) * SH_BLOCK, SH_BLOCK
        rest, grad_rest = _arg(sh_rest.view(-1), wp.float32), _arg(grad_sh_rest.view(-1), wp.float32)
    else:  # CUDA: one thread per SH coefficient (half-warp shuffles); CPU: one per Gaussian
        kernel = sh_to_color_grouped_backward_kernel if cuda else sh_to_color_backward_kernel
        dim, block = n * (MAX_SH_COEFFICIENTS if cuda else 1), None
        rest = None if sh_rest is None else _arg(sh_rest, wp.vec3)
        grad_rest = None if grad_sh_rest is None else _arg(grad_sh_rest, wp.vec3)
    dc_step, rest_step = _adam_steps(step, sh, sh_rest, radii)
    with _warp_scope(means.device):
        _launch(
            kernel,
            dim,
            inputs=[
                _arg(means, wp.vec3),
                _arg(sh, wp.vec3),
                rest,
                sh_degree,
                camera.center,
                _on_device(camera, means.device),
                _arg(radii, wp.vec2i),
                _arg(colors, wp.vec3),
                _arg(grad_colors, wp.vec3),
                dc_step,
                rest_step,
            ],
            outputs=[_arg(grad_means, wp.vec3), _arg(grad_sh, wp.vec3), grad_rest],
            block_dim=block,
        )
    if step is not None:  # updated in place: as an in-place op would, tell torch
        increment_version(sh)
        increment_version(sh_rest)
        return grad_means, None, None
    return grad_means, grad_sh, grad_sh_rest


class _Blend(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, means2d, conics, colors, opacities, depths, background, bins: TileBins, width, height, absgrad_request
    ):
        device = means2d.device
        image = means2d.new_empty(height, width, 3)
        transmittance = means2d.new_empty(height, width)
        depth_sum = means2d.new_empty(height, width)
        last = torch.empty(height, width, dtype=torch.int32, device=device)
        chunk = _blend_chunk() if any(ctx.needs_input_grad[:5]) else 0  # checkpoints only for a backward
        num_tiles = bins.tiles_x * bins.tiles_y
        checkpoints = (None, None, None)
        if chunk:  # the colour and transmittance at each chunk boundary, and each tile's walk
            rows = bins.num_intersections // chunk + num_tiles
            checkpoints = (
                means2d.new_empty(rows, BLOCK_SIZE, 4),
                means2d.new_empty(rows, BLOCK_SIZE),
                torch.full((num_tiles,), -1, dtype=torch.int32, device=device),
            )
        with _warp_scope(device):
            _launch(
                blend_forward_chunked_kernel if chunk else blend_forward_kernel,
                num_tiles * BLOCK_SIZE,
                inputs=[
                    bins.tile_ranges,
                    bins.sorted_gauss_ids,
                    *_blend_gaussian_inputs(means2d, conics, colors, opacities, depths),
                    _arg(background, wp.vec3),
                    width,
                    height,
                    bins.tiles_x,
                    chunk,
                ],
                outputs=[
                    _arg(image, wp.vec3),
                    _arg(transmittance, wp.float32),
                    _arg(depth_sum, wp.float32),
                    _arg(last, wp.int32),
                    *(
                        None if t is None else _arg(t, dtype)
                        for t, dtype in zip(checkpoints, (wp.vec4, wp.float32, wp.int32))
                    ),
                ],
                block_dim=BLOCK_SIZE,
            )
        saved = (image, depth_sum) if chunk else ()
        ctx.save_for_backward(means2d, conics, colors, opacities, depths, background, transmittance, last, *saved)
        ctx.chunk = chunk
        ctx.checkpoints = checkpoints
        ctx.bins = bins
        ctx.absgrad_request = absgrad_request
        ctx.mark_non_differentiable(last)
        ctx.set_materialize_grads(False)  # an output the loss does not use gets None, not zeros
        return image, transmittance, depth_sum, last

    @staticmethod
    def backward(ctx, grad_image, grad_transmittance, grad_depth_sum, _grad_last):
        means2d, conics, colors, opacities, depths, background, transmittance, last, *saved = ctx.saved_tensors
        bins = ctx.bins
        height, width = transmittance.shape
        grad_image = means2d.new_zeros(height, width, 3) if grad_image is None else grad_image.contiguous()
        # alpha = 1 - transmittance: a gradient on transmittance is minus one on alpha.
        grad_alpha = None if grad_transmittance is None else -grad_transmittance.contiguous()
        n = means2d.shape[0]
        # The depth gradients and the AbsGS sums cost a sixth of the kernel: only when the loss
        # uses the depth sum or ``info.retain_absgrad()`` asked for the sums.
        absgrad = ctx.absgrad_request.get("sums")
        sums = grad_depth_sum is not None or absgrad is not None
        if sums:
            grad_depth_sum = _grad_or_zeros(grad_depth_sum, transmittance)
            if absgrad is None:
                absgrad = means2d.new_zeros(n, 2)
        # One zero fill for all the gradients the kernel adds to: [means2d | conics | colors | opacities (| depths)].
        sizes = [2 * n, 3 * n, 3 * n, n] + ([n] if sums else [])
        grads = [
            part.view(t.shape)
            for part, t in zip(means2d.new_zeros(sum(sizes)).split(sizes), (means2d, conics, colors, opacities, depths))
        ]
        grad_outputs = [
            *_blend_gaussian_inputs(*grads[:4], grads[4] if sums else None),
            _arg(absgrad, wp.vec2) if sums else None,
        ]
        num_tiles = bins.tiles_x * bins.tiles_y
        chunk, blocks = ctx.chunk, num_tiles
        chunk_ends = image = depth_sum = None
        with _warp_scope(means2d.device):
            if chunk:  # each tile's walk in chunks: their table, and a block for every chunk there may be
                image, depth_sum = saved
                counts = torch.empty(num_tiles, dtype=torch.int32, device=means2d.device)
                chunk_ends = torch.empty_like(counts)
                _launch(
                    walk_chunks_kernel,
                    num_tiles,
                    inputs=[bins.tile_ranges, _arg(ctx.checkpoints[2], wp.int32), chunk],
                    outputs=[_arg(counts, wp.int32)],
                )
                wp.utils.array_scan(
                    wp.from_torch(counts, dtype=wp.int32), wp.from_torch(chunk_ends, dtype=wp.int32), inclusive=True
                )
                blocks = num_tiles + bins.num_intersections // chunk
            checkpoint_color, checkpoint_depth = ctx.checkpoints[:2]
            _launch(
                _blend_backward_kernel(sums, means2d.device.type == "cuda"),
                blocks * BLOCK_SIZE,
                inputs=[
                    bins.tile_ranges,
                    bins.sorted_gauss_ids,
                    *_blend_gaussian_inputs(means2d, conics, colors, opacities, depths),
                    _arg(background, wp.vec3),
                    width,
                    height,
                    bins.tiles_x,
                    chunk,
                    None if chunk_ends is None else _arg(chunk_ends, wp.int32),
                    _arg(transmittance, wp.float32),
                    _arg(last, wp.int32),
                    None if image is None else _arg(image, wp.vec3),
                    None if depth_sum is None else _arg(depth_sum, wp.float32),
                    None if checkpoint_color is None else _arg(checkpoint_color, wp.vec4),
                    None if checkpoint_depth is None else _arg(checkpoint_depth, wp.float32),
                    _arg(grad_image, wp.vec3),
                    None if grad_alpha is None else _arg(grad_alpha, wp.float32),
                    _arg(grad_depth_sum, wp.float32) if sums else None,
                ],
                outputs=grad_outputs,
                block_dim=BLOCK_SIZE,
            )
        if not sums:
            grads.append(None)  # no gradient reaches the depths
        grad_background = None
        if ctx.needs_input_grad[5]:
            grad_background = (transmittance.unsqueeze(-1) * grad_image).sum(dim=(0, 1))
        return (*grads, grad_background, None, None, None, None)


def _blend_chunk() -> int:
    """``BLEND_CHUNK``, checked: 0 or a positive multiple of BLOCK_SIZE."""
    if not isinstance(BLEND_CHUNK, int) or BLEND_CHUNK < 0 or BLEND_CHUNK % BLOCK_SIZE:
        raise ValueError(f"cdcgs.render.BLEND_CHUNK must be 0 or a multiple of {BLOCK_SIZE}, got {BLEND_CHUNK!r}")
    return BLEND_CHUNK


def _blend_backward_kernel(sums: bool, cuda: bool):
    """The blend adjoint's kernel: with or without the depth and AbsGS sums, and on CUDA the one
    ``BLEND_BACKWARD_CUDA`` names."""
    if BLEND_BACKWARD_CUDA not in ("block", "warp"):
        raise ValueError(f"cdcgs.render.BLEND_BACKWARD_CUDA must be 'block' or 'warp', got {BLEND_BACKWARD_CUDA!r}")
    if cuda and BLEND_BACKWARD_CUDA == "warp":
        return blend_backward_warp_kernel if sums else blend_backward_lean_warp_kernel
    return blend_backward_kernel if sums else blend_backward_lean_kernel


def _blend_gaussian_inputs(means2d, conics, colors, opacities, depths):
    depths = None if depths is None else _arg(depths, wp.float32)
    return [_arg(means2d, wp.vec2), _arg(conics, wp.vec3), _arg(colors, wp.vec3), _arg(opacities, wp.float32), depths]


# --------------------------------------------------------------------------------------------
# Validation


def _check_tensor(name: str, value, shape: tuple, device: torch.device | None) -> torch.Tensor:
    """``shape`` uses None for the free Gaussian-count dimension and -1 for 'any size'."""
    if not isinstance(value, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype != torch.float32:
        raise ValueError(f"{name} must be float32, got {value.dtype}")
    if value.dim() != len(shape) or not all(s is None or s == -1 or s == v for s, v in zip(shape, value.shape)):
        expected = "[" + ", ".join("N" if s is None else ("*" if s == -1 else str(s)) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {expected}, got {list(value.shape)}")
    if device is not None and value.device != device:
        raise ValueError(
            f"{name} is on {value.device} but means is on {device}; all Gaussian tensors must share a device"
        )
    return value.contiguous()


# Threads of the finiteness check: enough to keep a large GPU's memory busy, each looping over
# its share (one thread per value cost ~0.4 ms more at 3M Gaussians on an H100).
_CHECK_THREADS = 1 << 18


# --------------------------------------------------------------------------------------------
# Cameras


@dataclass(frozen=True, eq=False)
class PreparedCamera:
    """A pinhole camera checked once and built for the kernels: ``rasterize(..., camera=prepared)``.

    Made by :func:`prepare_camera`. A caller that renders the same views again and again (a
    training, an evaluation, a viewer) keeps one per view and skips the checks and the building
    that ``rasterize(viewmat=..., K=...)`` repeats on every call. Immutable; a moved camera is a new
    one.

    Attributes:
        width, height: image size in pixels.
        near_plane: Gaussians with camera z below this are culled.
        camera: the Warp :class:`cdcgs.kernels.Camera` struct the projection kernel reads
            (world-to-camera rotation and translation, intrinsics, image size, near plane).
        center: the camera centre in world coordinates, -R^T t (``wp.vec3``), from which the SH
            colour's view directions start.
        on_device: None, or a Warp array of one :class:`cdcgs.kernels.Camera` on the render's
            device that the kernels read instead of ``camera`` and ``center``: a step replayed as
            a CUDA graph writes its view's camera there on the device (:func:`select_camera`).
            Every camera written there must have this one's size and near plane.
    """

    width: int
    height: int
    near_plane: float
    camera: Camera
    center: wp.vec3
    on_device: wp.array | None = None


def prepare_camera(viewmat, K, width: int, height: int, near_plane: float = 0.01) -> PreparedCamera:
    """Check a pinhole camera and build it for the kernels, once.

    Args:
        viewmat: [4, 4] world-to-camera matrix (camera x right, y down, z forward), a rotation and a
            translation. K: [3, 3] intrinsics in pixels; (cx, cy) continuous, pixel (i, j) centred at
            (i+0.5, j+0.5). Either may be a tensor on any device, a numpy array or nested lists
            (read on the host, in float64).
        width, height: image size in pixels (positive ints).
        near_plane: Gaussians with camera z below this are culled (positive, finite).

    Returns:
        A :class:`PreparedCamera` for ``rasterize(..., camera=...)``.

    Raises:
        ValueError: a matrix of the wrong shape, with non-finite entries, a viewmat that is not a
            rotation and translation, non-positive focal lengths, image size or near plane.
    """
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ValueError(f"{name} must be a positive int (pixels), got {value!r}")
    if not (isinstance(near_plane, (int, float)) and math.isfinite(near_plane) and near_plane > 0):
        raise ValueError(f"near_plane must be a positive finite number, got {near_plane!r}")
    mats = {}
    for name, value, size in (("viewmat", viewmat, 4), ("K", K, 3)):
        # numpy, not torch: without a PreparedCamera these checks run on every render, and torch's
        # per-op overhead showed
        try:
            if isinstance(value, torch.Tensor):
                value = value.detach().to("cpu", torch.float64).numpy()
            mat = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(f"{name} must be a {size}x{size} matrix: {err}") from None
        if mat.shape != (size, size):
            raise ValueError(f"{name} must have shape [{size}, {size}], got {list(mat.shape)}")
        if not np.isfinite(mat).all():
            raise ValueError(f"{name} has non-finite entries")
        mats[name] = mat
    view, intr = mats["viewmat"], mats["K"]
    if not np.allclose(view[3], [0.0, 0.0, 0.0, 1.0], rtol=1e-5, atol=1e-8):
        raise ValueError(f"viewmat's last row must be [0, 0, 0, 1], got {view[3].tolist()}")
    rotation = view[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), rtol=1e-5, atol=1e-4):
        raise ValueError("viewmat's upper-left 3x3 block must be a rotation (world-to-camera, no scale)")
    if intr[0, 0] <= 0 or intr[1, 1] <= 0:
        raise ValueError(f"K must have positive focal lengths, got fx={intr[0, 0]}, fy={intr[1, 1]}")
    camera = make_camera(view, intr, width, height, near_plane)
    center = wp.vec3(camera.center[0], camera.center[1], camera.center[2])
    return PreparedCamera(width=width, height=height, near_plane=float(near_plane), camera=camera, center=center)


def _resolve_camera(camera, viewmat, K, width, height, near_plane) -> PreparedCamera:
    """The camera of a ``rasterize`` call: the prepared one, or one checked and built now."""
    loose = {"viewmat": viewmat, "K": K, "width": width, "height": height}
    if camera is not None:
        given = [name for name, value in loose.items() if value is not None] + (
            ["near_plane"] if near_plane is not None else []
        )
        if given:
            raise ValueError(
                f"pass either camera (a PreparedCamera) or viewmat, K, width and height, not both (also got {', '.join(given)})"
            )
        if not isinstance(camera, PreparedCamera):
            raise ValueError(
                f"camera must be a PreparedCamera (from cdcgs.render.prepare_camera), got {type(camera).__name__}"
            )
        return camera
    missing = [name for name, value in loose.items() if value is None]
    if missing:
        raise ValueError(
            f"pass viewmat, K, width and height, or camera=prepare_camera(...); missing: {', '.join(missing)}"
        )
    return prepare_camera(viewmat, K, width, height, 0.01 if near_plane is None else near_plane)


# --------------------------------------------------------------------------------------------
# Entry point


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    sh: torch.Tensor | None = None,
    *,
    sh_rest: torch.Tensor | None = None,
    viewmat=None,
    K=None,
    width: int | None = None,
    height: int | None = None,
    camera: PreparedCamera | None = None,
    sh_degree: int | None = None,
    colors: torch.Tensor | None = None,
    background=None,
    antialiased: bool = False,
    near_plane: float | None = None,
    render_depth: bool = False,
    capacity: int | None = None,
    sh_step: ShAdamStep | None = None,
) -> tuple[torch.Tensor, torch.Tensor, RasterizeInfo]:
    """Render 3D Gaussians from one pinhole camera, differentiably.

    Args:
        means: [N, 3] world positions. quats: [N, 4] rotations (w, x, y, z), normalised inside.
        scales: [N, 3] standard deviations along the Gaussian's axes (not log).
        opacities: [N] opacities in [0, 1] (after the sigmoid).
        sh: [N, K, 3] real spherical-harmonics coefficients, 3DGS convention, K >= (sh_degree+1)^2.
        sh_rest: with it, ``sh`` holds the degree-0 coefficients [N, 1, 3] and ``sh_rest`` the
            others [N, K - 1, 3], as a trainer keeps them (the render then concatenates nothing).
        viewmat: [4, 4] world-to-camera matrix (camera x right, y down, z forward). K: [3, 3]
            intrinsics in pixels; (cx, cy) continuous, pixel (i, j) centred at (i+0.5, j+0.5).
            Either may be a tensor on any device, a numpy array or nested lists (read on the host).
        width, height: image size in pixels.
        camera: instead of viewmat, K, width, height (and near_plane): a :class:`PreparedCamera`
            from :func:`prepare_camera`, checked and built once. Exactly one of the two ways.
        sh_degree: 0..3, degree of ``sh`` to evaluate; default sqrt(K) - 1.
        colors: [N, 3] colours to composite instead of ``sh`` (exactly one of the two).
        background: [3] colour behind the Gaussians (tensor or sequence); default black.
            Differentiable when it is a tensor that requires grad.
        antialiased: multiply opacity by sqrt(det cov / det dilated cov) (Mip-Splatting).
        near_plane: Gaussians with camera z below this are culled (default 0.01; with ``camera``,
            the prepared camera's).
        render_depth: also return the expected depth map in ``info.depth``.
        capacity: bin the view's (tile, Gaussian) pairs into this many slots (at most
            ``MAX_CAPACITY``) instead of reading their count on the host: with a ``camera`` (or
            viewmat and K on the host) the render then never waits for the device, and it checks
            nothing it would have to read back. Call ``info.check()`` later, before using the
            result (e.g. before an optimizer step): it raises NonFiniteError for an input that held
            NaN or inf and CapacityError (with ``.needed``) when the pairs did not fit, in which
            case the image and the gradients are wrong; otherwise the image, alpha and gradients
            are those of a render without ``capacity``. The sort's work grows with it.
        sh_step: a :class:`ShAdamStep`: the backward pass applies this Adam step to ``sh`` and
            ``sh_rest`` (both needed) in place and gives them no gradient (a training step's
            update fused into the SH adjoint; the step's rates are read when the adjoint runs).

    Returns:
        image [H, W, 3], alpha [H, W] and a :class:`RasterizeInfo`. All float32 on ``means``' device.

    Raises:
        ValueError: an argument of the wrong type, dtype, shape or device, non-finite values (in
            ``sh``: those of the Gaussians in view, the only ones read), an empty scene or an empty
            image, both or neither of ``camera`` and viewmat/K/width/height; the message names the
            argument.
    """
    given = (sh, sh_rest)  # the checks below may copy: a step must update these
    means = _check_tensor("means", means, (None, 3), None)
    device = means.device
    n = means.shape[0]
    if n == 0:
        raise ValueError("means is empty: the scene has no Gaussians to render")
    quats = _check_tensor("quats", quats, (n, 4), device)
    scales = _check_tensor("scales", scales, (n, 3), device)
    opacities = _check_tensor("opacities", opacities, (n,), device)
    if (sh is None) == (colors is None):
        raise ValueError("pass exactly one of sh ([N, K, 3] coefficients) and colors ([N, 3])")
    if sh_rest is not None and sh is None:
        raise ValueError("sh_rest needs sh (its degree-0 coefficients, [N, 1, 3])")
    if sh is not None:
        sh = _check_tensor("sh", sh, (n, 1 if sh_rest is not None else -1, 3), device)
        k = sh.shape[1]
        if sh_rest is not None:
            sh_rest = _check_tensor("sh_rest", sh_rest, (n, -1, 3), device)
            k += sh_rest.shape[1]
        if sh_degree is None:
            sh_degree = math.isqrt(k) - 1
            if (sh_degree + 1) ** 2 != k:
                raise ValueError(f"sh has {k} coefficients per channel, not a square; pass sh_degree")
        if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= MAX_SH_DEGREE:
            raise ValueError(f"sh_degree must be an int in 0..{MAX_SH_DEGREE}, got {sh_degree!r}")
        if k < (sh_degree + 1) ** 2:
            raise ValueError(f"sh has {k} coefficients per channel, degree {sh_degree} needs {(sh_degree + 1) ** 2}")
    else:
        colors = _check_tensor("colors", colors, (n, 3), device)
    background_tensor = isinstance(background, torch.Tensor)  # checked on the device below
    if background is None:
        background = means.new_zeros(3)
    elif background_tensor:
        background = _check_tensor("background", background, (3,), device)
    else:
        try:
            values = [float(v) for v in background]
        except (TypeError, ValueError):
            raise ValueError(f"background must be 3 numbers or a [3] tensor, got {background!r}") from None
        if len(values) != 3:
            raise ValueError(f"background must have 3 entries, got {len(values)}")
        if not all(math.isfinite(v) for v in values):
            raise NonFiniteError("background")
        background = means.new_tensor(values)
    _check_capacity(capacity)
    _check_sh_step(sh_step, sh, sh_rest, device, given)
    prepared = _resolve_camera(camera, viewmat, K, width, height, near_plane)
    width, height = prepared.width, prepared.height

    # One Warp scope for the whole forward pass (the autograd functions' own scopes nest for free).
    with _warp_scope(device):
        checked = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "background": background}
        checked["sh" if sh is not None else "colors"] = sh if sh is not None else colors
        # Flags for the tensors holding NaN or inf, raised by the kernels that read them anyway: the
        # projection (means, quats, scales, opacities) and the colouring (``sh``, of the Gaussians in
        # view, the only ones that reach the image). Only a background tensor and ``colors`` are read
        # by a check of their own. The flags travel with the intersection count below, so validation
        # costs no extra host synchronisation.
        nonfinite = torch.zeros(len(checked), dtype=torch.int32, device=device)
        own_check = [background if background_tensor else background[:0], colors if sh is None else means[:0]]
        if any(t.numel() for t in own_check):
            flat = [means[:0].view(-1)] * 4 + [t.view(-1) for t in own_check]
            threads = min(max(t.numel() for t in flat), _CHECK_THREADS)
            _launch(
                find_nonfinite_kernel,
                threads,
                inputs=[*(_arg(t, wp.float32) for t in flat), threads],
                outputs=[_arg(nonfinite, wp.int32)],
            )

        means2d, conics, depths, composited_opacities, radii = _Project.apply(
            means, quats, scales, opacities, prepared, antialiased, nonfinite
        )
        if sh is not None:
            colors = _ShColor.apply(
                means, sh, sh_rest, sh_degree, prepared, radii, nonfinite[len(checked) - 1 :], sh_step
            )

        pending = None
        if capacity is None:
            read_count = _count_reader(nonfinite, list(checked))
            bins = _bin(means2d, radii, depths, conics, composited_opacities, width, height, read_count)
        else:  # nothing read back: the flags, the overflow and the count wait for info.check()
            start = _start_bin(means2d, radii, depths, conics, composited_opacities, width, height)
            bins, overflow = finish_binning_within(start, capacity)
            pending = torch.cat([nonfinite, _torch(overflow), _torch(start.offsets)[-1:]])
        absgrad_request = {}  # info.retain_absgrad() puts the AbsGS sums' tensor here for the backward pass
        image, transmittance, depth_sum, last = _Blend.apply(
            means2d, conics, colors, composited_opacities, depths, background, bins, width, height, absgrad_request
        )
    alpha = 1.0 - transmittance
    depth = None
    if render_depth:
        depth = torch.where(alpha > 0, depth_sum / alpha.clamp_min(1e-10), torch.zeros_like(depth_sum))
    projection = (means2d, conics, depths, composited_opacities, radii)
    info = _info(width, height, projection, bins, colors, last, transmittance, depth, absgrad_request)
    if pending is not None:
        info.pending, info._pending_names = pending, tuple(checked)
        if device.type == "cuda":
            info._pending_stream = torch.cuda.current_stream(device)
    return image, alpha, info


def _check_capacity(capacity) -> None:
    if capacity is not None and (
        isinstance(capacity, bool) or not isinstance(capacity, int) or not 1 <= capacity <= MAX_CAPACITY
    ):
        raise ValueError(
            f"capacity must be a positive int up to {MAX_CAPACITY}, slots for the view's (tile, Gaussian) pairs; "
            f"got {capacity!r}"
        )


def _info(width, height, projection, bins, colors, last, transmittance, depth, absgrad) -> RasterizeInfo:
    means2d, conics, depths, opacities, radii = projection
    return RasterizeInfo(
        width=width,
        height=height,
        tile_size=TILE_SIZE,
        means2d=means2d,
        conics=conics,
        depths=depths,
        opacities=opacities,
        colors=colors,
        radii=radii,
        tile_counts=_torch(bins.tile_counts),
        num_intersections=bins.num_intersections,
        tile_ranges=_torch(bins.tile_ranges),
        sorted_gauss_ids=_torch(bins.sorted_gauss_ids),
        last_contributor=last,
        transmittance=transmittance,
        depth=depth,
        _absgrad=absgrad,
    )


class PendingBins:
    """A view's projection and the first half of its binning, queued on the device, with the
    intersection count and the finiteness flags on their way to the host (on CUDA an
    asynchronous copy into pinned memory and an event). :meth:`finish` waits for that copy alone,
    not for the work queued after it, and queues the rest. Made by :func:`start_bin_view`.

    A loop over views that starts view ``i + 1`` before it finishes view ``i`` keeps the GPU busy
    while the host waits for a count and then queues the sort: what CDC-GS's Γ pass does
    (:func:`cdcgs.complexity.complexity_over_views`). The second half runs on the CUDA stream that
    was current at the start, whichever is current at ``finish``.
    """

    def __init__(self, camera: PreparedCamera, projection: tuple, start: BinningStart, nonfinite, names):
        self._camera, self._projection, self._start, self._names = camera, projection, start, names
        self._info: RasterizeInfo | None = None
        values = torch.cat([nonfinite, _torch(start.offsets)[-1:]])
        self.count_on_device = values[-1:]  # the intersection count, int32 [1], for a caller that reads many at once
        self._event = self._stream = None
        if values.device.type == "cuda":
            self._stream = torch.cuda.current_stream(values.device)  # the first half's, and Warp's
            self._values = values  # alive until the copy has read it
            self._host = torch.empty(values.shape, dtype=values.dtype, pin_memory=True)
            self._host.copy_(values, non_blocking=True)
            self._event = torch.cuda.Event()
            self._event.record(self._stream)
        else:
            self._host = values

    @torch.no_grad()
    def finish(self) -> RasterizeInfo:
        """The view's :class:`RasterizeInfo`, as :func:`bin_view` returns it (the same one on a
        second call). Raises :class:`cdcgs.errors.NonFiniteError` naming a tensor with NaN or inf."""
        if self._info is not None:
            return self._info
        if self._event is not None:
            self._event.synchronize()  # the count alone: later work on the stream goes on
        values = self._host.tolist()
        for name, bad in zip(self._names, values[:-1]):
            if bad:
                raise NonFiniteError(name)
        camera = self._camera
        stream = contextlib.nullcontext() if self._stream is None else torch.cuda.stream(self._stream)
        with stream, _warp_scope(self._projection[0].device):
            bins = finish_binning(self._start, values[-1])
        self._info = _info(camera.width, camera.height, self._projection, bins, None, None, None, None, {})
        self._start = self._values = None  # the first half's buffers are the info's now, or spent
        return self._info


@torch.no_grad()
def start_bin_view(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    *,
    camera: PreparedCamera,
    antialiased: bool = False,
) -> PendingBins:
    """:func:`bin_view` in two halves: this queues the projection and the first half of the
    binning and returns at once; ``.finish()`` on the result reads the intersection count and
    returns the view's :class:`RasterizeInfo`. Same arguments and errors as :func:`bin_view` (the
    non-finite ones from ``finish``)."""
    return PendingBins(*_start_view(means, quats, scales, opacities, camera, antialiased))


def _start_view(means, quats, scales, opacities, camera, antialiased):
    """The checks, the projection and the first half of the binning of a view: (camera,
    projection, binning start, finiteness flags, the checked names)."""
    means = _check_tensor("means", means, (None, 3), None)
    device = means.device
    n = means.shape[0]
    if n == 0:
        raise ValueError("means is empty: the scene has no Gaussians to render")
    checked = {
        "means": means,
        "quats": _check_tensor("quats", quats, (n, 4), device),
        "scales": _check_tensor("scales", scales, (n, 3), device),
        "opacities": _check_tensor("opacities", opacities, (n,), device),
    }
    if not isinstance(camera, PreparedCamera):
        raise ValueError(
            f"camera must be a PreparedCamera (from cdcgs.render.prepare_camera), got {type(camera).__name__}"
        )
    with _warp_scope(device):
        nonfinite = torch.zeros(len(checked), dtype=torch.int32, device=device)
        projection = _project(*checked.values(), camera, antialiased, nonfinite)
        means2d, conics, depths, composited_opacities, radii = projection
        start = _start_bin(means2d, radii, depths, conics, composited_opacities, camera.width, camera.height)
    return camera, projection, start, nonfinite, list(checked)


@torch.no_grad()
def bin_view(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    *,
    camera: PreparedCamera,
    antialiased: bool = False,
    capacity: int | None = None,
) -> RasterizeInfo:
    """The projection and the depth-sorted tile lists of one view, without colours or an image.

    What the kernels that walk the tile lists by themselves need (CDC-GS's Γ pass,
    :func:`cdcgs.complexity.gaussian_complexity`): a render less its colours and its blend, and
    without autograd. The arguments are :func:`rasterize`'s, the camera prepared. The returned
    info's ``colors``, ``last_contributor``, ``transmittance`` and ``depth`` are None.
    ``capacity``: as :func:`rasterize`'s, the pairs binned into that many slots without reading
    their count; ``info.check()`` (or its ``pending`` flags read later) then says whether they fit
    and whether an input held NaN or inf, and the lists are wrong when they did not fit.

    Raises:
        ValueError: as :func:`rasterize`: an argument of the wrong type, dtype, shape or device,
            non-finite values (naming the tensor; with ``capacity``, from ``info.check()``), an
            empty scene, a camera that is not prepared, a capacity out of range.
    """
    if capacity is None:
        return start_bin_view(means, quats, scales, opacities, camera=camera, antialiased=antialiased).finish()
    _check_capacity(capacity)
    camera, projection, start, nonfinite, names = _start_view(means, quats, scales, opacities, camera, antialiased)
    with _warp_scope(projection[0].device):
        bins, overflow = finish_binning_within(start, capacity)
    info = _info(camera.width, camera.height, projection, bins, None, None, None, None, {})
    info.pending, info._pending_names = (
        torch.cat([nonfinite, _torch(overflow), _torch(start.offsets)[-1:]]),
        tuple(names),
    )
    if info.pending.device.type == "cuda":
        info._pending_stream = torch.cuda.current_stream(info.pending.device)
    return info
