"""Sharded Gaussians: the render of a step whose processes each hold a slice of the scene.

Data parallelism (:mod:`cdcgs.train.distributed`) keeps every Gaussian on every process and
all-reduces 59 gradients a Gaussian each step. Here process s holds only its own slice, ``rows[s]``
Gaussians (the slices of processes 0, 1, ... in order make up the scene), and renders one view of
the step, ``cameras[s]``. :func:`rasterize_shard` is that render, differentiable, on every process
at once:

1. each process projects its slice into every process's view and colours it from that view
   (the projection and the SH evaluation of :func:`cdcgs.render.rasterize`);
2. one all-to-all sends each view's part to the process that renders the view: per Gaussian its 2D
   mean, conic, colour, opacity and depth (10 floats) and its screen radii (2, exact as floats);
3. that process bins, sorts and blends the whole scene's projection into its view, as one process
   rendering every Gaussian would, Gaussian for Gaussian in the same order;
4. in the backward pass the gradients of those 10 floats go back by the reverse all-to-all, and
   each process finishes the projection's and the SH evaluation's adjoints of its own slice, for
   every view: its parameters' gradients are the step's (the sum over the views), with nothing
   all-reduced.

A step thus moves 12 floats a Gaussian forward and 10 back, against data parallelism's all-reduce
of 59, and no process holds another's parameters, gradients or Adam moments. By default every
projected Gaussian goes to every view, visible or not (fixed sizes: one all-to-all with the
slices' sizes); ``visible_only`` sends a view only the Gaussians it sees. The render reads its
intersection count on the host, as :func:`cdcgs.render.rasterize` without ``capacity``.

This module is the render; a training on shards (densification per slice, Adam per slice, the
evaluation and the files gathered) builds on it and is not there yet.
"""

from __future__ import annotations

import torch
import torch.distributed as dist

from .._interop import warp_scope
from ..kernels._constants import MAX_SH_DEGREE
from ..render import (
    PreparedCamera,
    RasterizeInfo,
    _bin,
    _Blend,
    _check_tensor,
    _count_reader,
    _info,
    _Project,
    _ShColor,
)

__all__ = ["FIELDS", "rasterize_shard"]

# Floats sent per Gaussian and view: 2D mean 2, conic 3, colour 3, opacity 1, depth 1 (the
# DIFFERENTIABLE ones, whose gradients come back), then the screen radii 2.
FIELDS = 12
DIFFERENTIABLE = 10
_NAMES = ("means", "quats", "scales", "opacities", "sh")


class _Exchange(torch.autograd.Function):
    """An all-to-all of rows, and of their gradients back."""

    @staticmethod
    def forward(ctx, sent, send_rows: list[int], receive_rows: list[int], group, differentiable: int):
        received = sent.new_empty(sum(receive_rows), sent.shape[1])
        dist.all_to_all_single(received, sent.contiguous(), receive_rows, send_rows, group=group)
        ctx.rows = (send_rows, receive_rows)
        ctx.group = group
        ctx.differentiable = differentiable
        return received

    @staticmethod
    def backward(ctx, grad):
        """Only the first ``differentiable`` columns' gradients travel; the others' are zeros."""
        send_rows, receive_rows = ctx.rows
        columns = ctx.differentiable
        back = grad.new_zeros(sum(send_rows), grad.shape[1])
        moved = grad.new_empty(sum(send_rows), columns)
        dist.all_to_all_single(moved, grad[:, :columns].contiguous(), send_rows, receive_rows, group=ctx.group)
        back[:, :columns] = moved
        return back, None, None, None, None


def rasterize_shard(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    sh: torch.Tensor,
    *,
    sh_rest: torch.Tensor | None = None,
    sh_degree: int,
    cameras: list[PreparedCamera],
    rows: list[int],
    background: torch.Tensor | None = None,
    antialiased: bool = False,
    visible_only: bool = False,
    group=None,
) -> tuple[torch.Tensor, torch.Tensor, RasterizeInfo]:
    """This process's view of the whole scene, rendered from the slices of all processes.

    Every process of ``group`` (the default process group when None) calls it together, with its
    own slice: ``means`` [n, 3], ``quats`` [n, 4], ``scales`` [n, 3] (not log), ``opacities`` [n]
    (after the sigmoid) and ``sh`` [n, K, 3] (or its degree-0 part [n, 1, 3] and ``sh_rest`` the
    others [n, K - 1, 3], as a trainer keeps them), n = ``rows[rank]``; ``rows`` the slices' sizes of
    every process in rank order and ``cameras`` the view each process renders, both the same on
    every process. ``background``: [3] colour (default black). Returns the image [H, W, 3], the
    alpha [H, W] and the :class:`cdcgs.render.RasterizeInfo` of the view of this process, as
    :func:`cdcgs.render.rasterize` of the whole scene (the slices concatenated in rank order)
    with that camera returns them; its ``means2d`` etc. hold the whole scene's projection into
    this view. Gradients reach this process's slice from every process's view, so every process
    back-propagates through its image once (the backward pass holds the reverse exchange).
    ``visible_only``: send each view only the Gaussians it sees (screen radius above 0), at the
    cost of one more small exchange (the counts) and a read of them on the host; the image, alpha
    and gradients are the same, and ``info``'s per-Gaussian tensors hold the Gaussians the view
    sees and the first of each slice (so that no view receives none), in the slices' order.

    Unlike :func:`cdcgs.render.rasterize`: no ``render_depth`` and no ``capacity`` (the render reads
    its intersection count); ``background`` is not checked for NaN, and a background that requires
    grad gets this view's gradient alone. A wrong tensor on one process raises ValueError on every
    process (naming it on that one) before the exchange; NaN or inf in any slice raises
    NonFiniteError on every process.
    """
    rank, world = dist.get_rank(group), dist.get_world_size(group)
    if len(cameras) != world or not all(isinstance(c, PreparedCamera) for c in cameras):
        raise ValueError(f"cameras must be {world} PreparedCameras, one per process, got {cameras!r}")
    if len(rows) != world or any(isinstance(r, bool) or not isinstance(r, int) or r < 0 for r in rows):
        raise ValueError(f"rows must be {world} counts of Gaussians, one per process, got {rows!r}")
    if sum(rows) == 0:
        raise ValueError("rows are all 0: the scene has no Gaussians to render")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"every process's view must have one image size, got {sorted(sizes)}")
    if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be an int in 0..{MAX_SH_DEGREE}, got {sh_degree!r}")
    n = rows[rank]
    try:  # this process's tensors: a mistake here must not leave the others waiting in the exchange
        means = _check_tensor("means", means, (n, 3), None)
        device = means.device
        quats = _check_tensor("quats", quats, (n, 4), device)
        scales = _check_tensor("scales", scales, (n, 3), device)
        opacities = _check_tensor("opacities", opacities, (n,), device)
        sh = _check_tensor("sh", sh, (n, 1 if sh_rest is not None else -1, 3), device)
        k = sh.shape[1]
        if sh_rest is not None:
            sh_rest = _check_tensor("sh_rest", sh_rest, (n, -1, 3), device)
            k += sh_rest.shape[1]
        if k < (sh_degree + 1) ** 2:
            raise ValueError(f"sh has {k} coefficients per channel, degree {sh_degree} needs {(sh_degree + 1) ** 2}")
        if background is None:
            background = means.new_zeros(3)
        else:
            background = _check_tensor("background", background, (3,), device)
        wrong = None
    except ValueError as err:
        wrong = err
        cuda = dist.get_backend(group) == "nccl"
        device = torch.device("cuda", torch.cuda.current_device()) if cuda else torch.device("cpu")
    camera = cameras[rank]
    # This slice's flags of non-finite inputs, and one for a process's wrong arguments: reduced over
    # the processes before the exchange, so that all raise together or none does.
    flags = torch.zeros(len(_NAMES) + 1, dtype=torch.int32, device=device)
    nonfinite = flags[: len(_NAMES)]
    with warp_scope(device):
        parts = []
        if wrong is None:
            for view in cameras:
                means2d, conics, depths, composited, radii = _Project.apply(
                    means, quats, scales, opacities, view, antialiased, nonfinite
                )
                colors = _ShColor.apply(means, sh, sh_rest, sh_degree, view, radii, nonfinite[len(_NAMES) - 1 :])
                parts.append(
                    torch.cat([means2d, conics, colors, composited[:, None], depths[:, None], radii.float()], 1)
                )
        else:
            flags[-1] = 1
        dist.all_reduce(flags, op=dist.ReduceOp.MAX, group=group)
        if wrong is not None:
            raise wrong
        if int(flags[-1]) != 0:
            raise ValueError("another process's arguments to rasterize_shard were wrong (its error says which)")
        sent = torch.cat(parts)  # [W n, FIELDS], view by view; it needs the slice's gradients even when empty
        send_rows, receive_rows = [n] * world, list(rows)
        if visible_only:  # the rows of each view with a screen radius, and how many each process gets
            seen = (sent[:, FIELDS - 2 :] > 0).any(1).view(world, n)
            seen[:, :1] = True  # and each slice's first Gaussian, so that no view receives nothing
            counts = seen.sum(1)
            seen = seen.view(-1)
            incoming = torch.empty_like(counts)
            dist.all_to_all_single(incoming, counts, group=group)
            both = torch.cat([counts, incoming]).tolist()
            send_rows, receive_rows = both[:world], both[world:]
            sent = sent.index_select(0, seen.nonzero().squeeze(1))
        received = _Exchange.apply(sent, send_rows, receive_rows, group, DIFFERENTIABLE)

        means2d, conics, colors = received[:, 0:2], received[:, 2:5], received[:, 5:8]
        composited, depths = received[:, 8], received[:, 9]
        radii = received[:, 10:12].detach().to(torch.int32)
        means2d, conics, colors = (t.contiguous() for t in (means2d, conics, colors))
        composited, depths = composited.contiguous(), depths.contiguous()
        bins = _bin(
            means2d, radii, depths, conics, composited, camera.width, camera.height, _count_reader(nonfinite, _NAMES)
        )
        absgrad_request = {}  # info.retain_absgrad() puts the AbsGS sums' tensor here for the backward pass
        image, transmittance, _depth_sum, last = _Blend.apply(
            means2d, conics, colors, composited, depths, background, bins, camera.width, camera.height, absgrad_request
        )
    projection = (means2d, conics, depths, composited, radii)
    info = _info(camera.width, camera.height, projection, bins, colors, last, transmittance, None, absgrad_request)
    return image, 1.0 - transmittance, info
