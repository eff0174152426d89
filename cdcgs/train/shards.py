"""Sharded Gaussians: the render of a step whose processes each hold a slice of the scene.

Data parallelism (:mod:`cdcgs.train.distributed`) keeps every Gaussian on every process and
all-reduces 59 gradients a Gaussian each step. Here process s holds only its own slice, ``rows[s]``
Gaussians (the slices of processes 0, 1, ... in order make up the scene), and renders one view of
the step, ``cameras[s]``. :func:`rasterize_shard` is that render, differentiable, on every process
at once:

1. each process projects its slice into every process's view and colours it from that view
   (the projection and the SH evaluation of :func:`cdcgs.render.rasterize`);
2. one group of point-to-point transfers sends each view's part to the process that renders the
   view, field by field as the projection wrote it (no packing): per Gaussian its 2D mean, conic,
   colour, opacity and depth (10 floats) and its screen radii (2 int32), with each process's
   flags of wrong or non-finite inputs;
3. that process bins, sorts and blends the whole scene's projection into its view, as one process
   rendering every Gaussian would, Gaussian for Gaussian in the same order;
4. in the backward pass the gradients of those 10 floats go back the reverse way, and
   each process finishes the projection's and the SH evaluation's adjoints of its own slice, for
   every view: its parameters' gradients are the step's (the sum over the views), with nothing
   all-reduced. The transfers are posted first and waited for only when another process's view
   needs them, so the adjoints of the process's own view (which it projected last) run while they
   travel.

A step thus moves 12 numbers a Gaussian forward (10 floats, 2 int32) and 10 floats back, against
data parallelism's all-reduce of 59 floats, and no process holds another's parameters, gradients
or Adam moments. By default every projected Gaussian goes to every view, visible or not (fixed
sizes, known to every process); ``visible_only`` sends a view only the Gaussians it sees. The
render reads its intersection count on the host, as :func:`cdcgs.render.rasterize` without
``capacity``, and every process's flags with it: without ``visible_only`` nothing else waits for
the device. With ``capacity`` nothing is read on the host (``info.check()`` reads it later), so a
step can be captured as a CUDA graph.

This module is the render; the training on shards (``--dist-mode shards``: densification,
statistics and Adam per slice, the evaluation in rounds, the files gathered) is
:mod:`cdcgs.train.shard_training`.
"""

from __future__ import annotations

import torch
import torch.distributed as dist

from .._interop import device_clock, torch_tensor, warp_scope
from ..errors import PeerError
from ..kernels._constants import MAX_SH_DEGREE
from ..kernels.binning import finish_binning_within
from ..render import (
    PreparedCamera,
    RasterizeInfo,
    _bin,
    _Blend,
    _check_capacity,
    _check_tensor,
    _info,
    _Project,
    _raise_nonfinite,
    _ShColor,
    _start_bin,
)
from .distributed import RankFailed

__all__ = ["FIELDS", "rasterize_shard"]

# What a view receives of each Gaussian: 2D mean, conic, colour, opacity and depth (the
# differentiable fields, whose gradients go back), then the screen radii (int32).
FIELDS = (("means2d", 2), ("conics", 3), ("colors", 3), ("opacities", 1), ("depths", 1), ("radii", 2))
DIFFERENTIABLE = 5
_NAMES = ("means", "quats", "scales", "opacities", "sh")
_WRONG = len(_NAMES)  # the flag of a process whose arguments were wrong, after the non-finite ones
_FLAG_NAMES = (*_NAMES, PeerError.FLAG)


def _peer(group, rank: int) -> int:
    return rank if group is None else dist.get_global_rank(group, rank)


def _swap(outgoing: list[list[torch.Tensor]], incoming: list[list[torch.Tensor]], group, timer=None, pending=None):
    """Send ``outgoing[r]`` (a list of tensors) to process r and fill ``incoming[r]`` from it, for
    every r, as one group of point-to-point transfers: each tensor goes as it lies, with no packing
    (this process's own part is copied). Tensors with no elements are skipped on both sides; the
    processes agree on every size. ``timer`` ([wait, transfer] seconds, or None): the device's
    queued work is waited for, then the other processes (a one-number all-reduce), each added to
    its entry, then the transfers, timed to their end. ``pending`` (a :class:`_Pending`, without
    ``timer``): the transfers are posted and handed to it, not waited for; it keeps the tensors
    until it waits."""
    rank = dist.get_rank(group)
    ops = []
    for r, (sent, received) in enumerate(zip(outgoing, incoming)):
        if r == rank:
            for mine, into in zip(sent, received):
                into.copy_(mine)
            continue
        peer = _peer(group, r)
        ops += [dist.P2POp(dist.isend, t, peer, group, tag) for tag, t in enumerate(sent) if t.numel()]
        ops += [dist.P2POp(dist.irecv, t, peer, group, tag) for tag, t in enumerate(received) if t.numel()]
    if not ops:
        return
    try:
        if timer is not None:
            device = outgoing[rank][0].device
            start = device_clock(device)
            dist.all_reduce(torch.zeros(1, device=device), group=group)
            middle = device_clock(device)
            timer[0] += middle - start
        works = dist.batch_isend_irecv(ops)
        if pending is not None and timer is None:
            pending.hold(works, outgoing, incoming)
            return
        for work in works:
            work.wait()  # on NCCL: the current stream waits, not the host
        if timer is not None:
            timer[1] += device_clock(device) - middle
    except (RuntimeError, OSError) as err:  # gloo's word for a peer that died, stopped or timed out
        raise _failed(rank, err) from err


def _failed(rank: int, err: BaseException) -> BaseException:
    if isinstance(err, RankFailed):
        return err
    return RankFailed(
        f"rank {rank}: the sharded render's exchange failed; another process may have died, stopped or timed "
        f"out ({err})"
    )


class _Pending:
    """The backward pass's transfers, posted by :class:`_Exchange` and waited for by the first
    :class:`_AwaitGradients` that runs: in between, the autograd engine runs this process's own
    view's adjoints (created last, so taken first), on the device while the transfers run."""

    def __init__(self, rank: int):
        self.rank = rank
        self._works: list = []
        self._tensors: list = []  # what the transfers read and write, alive until they end

    def hold(self, works, *tensors) -> None:
        self.wait()  # none, unless a backward pass that posted them failed before its wait
        self._works, self._tensors = list(works), list(tensors)

    def wait(self) -> None:
        works, self._works = self._works, []
        try:
            for work in works:
                work.wait()  # on NCCL: the current stream waits, not the host
        except (RuntimeError, OSError) as err:
            raise _failed(self.rank, err) from err
        finally:
            self._tensors = []


class _AwaitGradients(torch.autograd.Function):
    """The identity on a view's fields that another process renders; in the backward pass it waits
    for the transfers that bring their gradients back (:class:`_Pending`) before the projection's
    adjoint of that view reads them."""

    @staticmethod
    def forward(ctx, pending, *fields):
        ctx.pending = pending
        return tuple(field.view_as(field) for field in fields)

    @staticmethod
    def backward(ctx, *grads):
        ctx.pending.wait()
        return (None, *grads)


class _Exchange(torch.autograd.Function):
    """Each view's fields to the process that renders it, field by field; their gradients back.

    Inputs: ``layout`` (send_rows, receive_rows, group, timer, pending: see :func:`_swap`); this process's
    flags, which every other process receives beside the fields; then the fields of view 0
    (FIELDS, in order), of view 1, .... Returns the received fields (each [sum(receive_rows),
    width], [sum(receive_rows)] where the width is 1, in process order) and the flags of every
    process [W, F]. The gradients are float32, as the fields."""

    @staticmethod
    def forward(ctx, layout, flags, *fields):
        send_rows, receive_rows, group, timer, _ = layout
        world = len(send_rows)
        per_view = [fields[v * len(FIELDS) : (v + 1) * len(FIELDS)] for v in range(world)]
        device = flags.device
        received = [
            torch.empty(sum(receive_rows), width, dtype=sample.dtype, device=device).squeeze(-1)
            for (_, width), sample in zip(FIELDS, per_view[0])
        ]
        every_flags = flags.new_empty(world, flags.shape[0])
        offsets = [sum(receive_rows[:r]) for r in range(world)]
        incoming = [
            [t[offsets[r] : offsets[r] + receive_rows[r]] for t in received] + [every_flags[r]] for r in range(world)
        ]
        _swap([[*per_view[r], flags] for r in range(world)], incoming, group, timer)
        ctx.layout = layout
        ctx.device = device
        ctx.mark_non_differentiable(received[-1], every_flags)
        return (*received, every_flags)

    @staticmethod
    def backward(ctx, *grads):
        """The differentiable fields' gradients travel back; the radii's and flags' are none."""
        send_rows, receive_rows, group, timer, pending = ctx.layout
        world = len(send_rows)
        offsets = [sum(receive_rows[:r]) for r in range(world)]
        device = ctx.device
        grads = [
            torch.zeros(sum(receive_rows), width, dtype=torch.float32, device=device).squeeze(-1)
            if g is None
            else g.contiguous()
            for g, (_, width) in zip(grads[:DIFFERENTIABLE], FIELDS)
        ]
        back = [
            [
                torch.empty(send_rows[v], width, dtype=torch.float32, device=device).squeeze(-1)
                for _, width in FIELDS[:DIFFERENTIABLE]
            ]
            for v in range(world)
        ]
        # posted, not waited for, where ``pending`` is given: the views of the other processes wait
        # in their _AwaitGradients, after this process's own view's adjoints are queued. Anomaly
        # mode reads every returned gradient for NaN as soon as this returns: it waits here.
        if torch.is_anomaly_enabled() and torch.is_anomaly_check_nan_enabled():
            pending = None
        outgoing = [[g[offsets[r] : offsets[r] + receive_rows[r]] for g in grads] for r in range(world)]
        _swap(outgoing, back, group, timer, pending)
        out = [None, None]
        for v in range(world):
            out += back[v] + [None]  # no gradient for the radii
        return tuple(out)


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
    capacity: int | None = None,
    group=None,
    exchange_timer: list[float] | None = None,
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

    ``capacity``: as :func:`cdcgs.render.rasterize`'s, the view's pairs binned into that many
    slots and nothing read back (not with ``visible_only``), so that the step can be captured as a
    CUDA graph: ``info.check()`` (after the backward pass, which every process must take) then
    raises what the render did not: a wrong argument of this process (ValueError naming it; the
    render went on with zeros for it, so that the others are not left waiting), NonFiniteError,
    PeerError for another process's wrong arguments, and CapacityError when this process's view
    overflowed its slots. That last one is this process's alone: a caller that stops on it must
    agree on it with the others first (e.g. an all-reduce of the flags), or they wait for it in
    the next exchange.

    ``exchange_timer``: [wait, transfer] seconds that every exchange of this render (forward, and
    the backward pass's) adds to: it waits for the device, then for the other processes (a
    one-number all-reduce: the wait), then times the transfers (for a step whose communication is
    measured: each wait holds the host back; every process must pass one or none).

    Unlike :func:`cdcgs.render.rasterize`: no ``render_depth``; ``background`` is not checked for
    NaN, and a background that requires grad gets this view's gradient alone. A wrong tensor on one
    process raises ValueError on every process (naming it on that one): that process takes its
    part in the exchange with zeros and raises after it, the others PeerError at their count read
    (with ``visible_only``, all at the read of the counts, before the fields are sent; with
    ``capacity``, all at ``info.check()``), so that none is left waiting in an exchange. NaN or inf
    in any slice raises NonFiniteError on every process, at the same read. The tensors must be on
    the CPU under gloo and on the process's current GPU under NCCL. Every process must pass the
    same ``rows``, ``cameras``, ``sh_degree``, ``antialiased``, ``visible_only`` and ``capacity``
    (None or not), and back-propagate through its image (the backward pass exchanges too).
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
    _check_capacity(capacity)
    if capacity is not None and visible_only:
        raise ValueError("capacity and visible_only: visible_only reads the counts on the host, capacity reads nothing")
    n = rows[rank]
    backend = str(dist.get_backend(group))  # "nccl", "gloo", or a mixed one that takes both
    try:  # this process's tensors: a mistake here must not leave the others waiting in the exchange
        means = _check_tensor("means", means, (n, 3), None)
        device = means.device
        if backend == "nccl" and device != torch.device("cuda", torch.cuda.current_device()):
            raise ValueError(f"means is on {device}: NCCL needs this process's tensors on its current GPU")
        if backend == "gloo" and device.type != "cpu":
            raise ValueError(f"means is on {device}: the process group's gloo takes CPU tensors")
        if device.type not in ("cpu", "cuda"):
            raise ValueError(f"means is on {device}: the render runs on the CPU or a CUDA GPU")
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
        cuda = backend != "gloo" and torch.cuda.is_available()
        device = torch.device("cuda", torch.cuda.current_device()) if cuda else torch.device("cpu")
        background = torch.zeros(3, dtype=torch.float32, device=device)  # with capacity the render goes on
    camera = cameras[rank]
    # This slice's flags of non-finite inputs, and one for this process's wrong arguments: every
    # process receives every other's with the fields, and all raise together at the render's count
    # read (or at the exchange of the counts; with capacity, at info.check()), so none is left
    # waiting in an exchange.
    flags = torch.zeros(len(_NAMES) + 1, dtype=torch.int32, device=device)
    nonfinite = flags[: len(_NAMES)]
    with warp_scope(device):
        views = [None] * world  # per view: the fields of FIELDS, of this slice
        # The backward pass's transfers overlap this process's own view's adjoints: the other views
        # are projected first, each behind an _AwaitGradients, and this process's own view last, so
        # that the autograd engine (later nodes first) queues its adjoints before any wait.
        transfers = _Pending(rank) if exchange_timer is None and not visible_only and wrong is None else None
        if wrong is None:
            for v in [*(v for v in range(world) if v != rank), rank]:
                view = cameras[v]
                means2d, conics, depths, composited, radii = _Project.apply(
                    means, quats, scales, opacities, view, antialiased, nonfinite
                )
                colors = _ShColor.apply(means, sh, sh_rest, sh_degree, view, radii, nonfinite[len(_NAMES) - 1 :], None)
                fields = [means2d, conics, colors, composited, depths]
                if transfers is not None and v != rank:
                    fields = list(_AwaitGradients.apply(transfers, *fields))
                views[v] = [*fields, radii]
        else:  # zeros of the right sizes take this process's part in the exchanges, both ways
            flags[_WRONG] = 1
            views = [[_zeros(n, width, device, name) for name, width in FIELDS] for _ in cameras]
        send_rows, receive_rows = [n] * world, list(rows)
        if visible_only:  # the rows of each view with a screen radius, and how many each process gets
            seen = [(fields[-1] > 0).any(1) for fields in views]
            for each in seen:
                each[:1] = True  # and each slice's first Gaussian, so that no view receives nothing
            counts = torch.stack([each.sum() for each in seen]).to(torch.int32)
            outgoing = [[torch.cat([counts[r : r + 1], flags])] for r in range(world)]
            incoming = torch.empty(world, 1 + flags.shape[0], dtype=torch.int32, device=device)
            _swap(outgoing, [[incoming[r]] for r in range(world)], group, exchange_timer)
            # the step's one read of the counts, both ways, and of every process's flags
            values = torch.cat([counts, incoming.amax(0)[1:], incoming[:, 0]]).tolist()
            _raise_flagged(wrong, values[world:-world])
            send_rows, receive_rows = values[:world], values[-world:]
            picked = [each.nonzero().squeeze(1) for each in seen]
            views = [[field.index_select(0, keep) for field in fields] for fields, keep in zip(views, picked)]
        *received, every_flags = _Exchange.apply(
            (send_rows, receive_rows, group, exchange_timer, transfers),
            flags,
            *(field for fields in views for field in fields),
        )
        if wrong is not None and capacity is None:  # the others raise at their count read
            every_flags.tolist()  # its transfers done before it raises (and perhaps leaves the group)
            raise wrong
        flags = every_flags.amax(0)
        means2d, conics, colors, composited, depths, radii = received
        pending = None
        if capacity is None:
            bins = _bin(means2d, radii, depths, conics, composited, camera.width, camera.height, _reader(flags))
        else:  # nothing read back: the flags, the overflow and the count wait for info.check()
            start = _start_bin(means2d, radii, depths, conics, composited, camera.width, camera.height)
            bins, overflow = finish_binning_within(start, capacity)
            pending = torch.cat([flags, torch_tensor(overflow), torch_tensor(start.offsets)[-1:]])
        absgrad_request = {}  # info.retain_absgrad() puts the AbsGS sums' tensor here for the backward pass
        image, transmittance, _depth_sum, last = _Blend.apply(
            means2d, conics, colors, composited, depths, background, bins, camera.width, camera.height, absgrad_request
        )
    projection = (means2d, conics, depths, composited, radii)
    info = _info(camera.width, camera.height, projection, bins, colors, last, transmittance, None, absgrad_request)
    if pending is not None:  # with a wrong argument here, the others raise at check() too
        info.pending, info._pending_names, info._deferred = pending, _FLAG_NAMES, wrong
        if device.type == "cuda":
            info._pending_stream = torch.cuda.current_stream(device)
    return image, 1.0 - transmittance, info


def _zeros(rows: int, width: int, device: torch.device, name: str) -> torch.Tensor:
    """A field of zeros; a float one requires grad, so that the backward pass exchanges too."""
    if name == "radii":
        return torch.zeros(rows, width, dtype=torch.int32, device=device)
    return torch.zeros(rows, width, device=device, dtype=torch.float32).squeeze(-1).requires_grad_(True)


def _raise_flagged(wrong: ValueError | None, flags: list[int]) -> None:
    """This process's own error, else NonFiniteError for a non-finite input or PeerError for
    another process's wrong arguments (the flags of every process combined)."""
    if wrong is not None:
        raise wrong
    _raise_nonfinite(_FLAG_NAMES, flags)


def _reader(flags: torch.Tensor):
    """``read_count`` for the binning: the intersection count and every process's flags, in the
    render's one host read."""

    def read_count(offsets) -> int:
        values = torch.cat([flags, torch_tensor(offsets)[-1:]]).tolist()
        _raise_flagged(None, values[:-1])
        return values[-1]

    return read_count
