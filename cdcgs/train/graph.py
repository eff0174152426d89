"""Training steps replayed as one CUDA graph (the default on CUDA where the training can take it;
``--cuda-graph`` to insist, ``--no-cuda-graph`` to train without).

A step's host work (Python, torch's autograd, some sixty launches) takes about as long as its
kernels below a million Gaussians, so the GPU waits for the host. With ``--cuda-graph`` the step
(for each of the process's views of the batch: render into slots, the note of its count, the loss,
the backward pass; then the strategy's statistics, the average over the batch (folded
into Adam's rates), the guard's records, one Adam launch; in a step of one view on one process the
SH coefficients' Adam step is taken by their adjoint instead, ``FUSE_SH_ADAM``) is captured once
under ``torch.cuda.graph``, Warp told of the capture, and replayed: per step the host only picks the
view and computes Adam's rates, writes them into pinned memory and queues two small copies and the
replay.

What a captured step reads that changes from step to step lives on the device:

- ``where`` (int32): the iteration and the view of each view the process renders in the step
  (``--batch-size`` over the processes: one pair each), then the flags and the step's views,
  copied from the host before each replay; a kernel
  (:data:`cdcgs.kernels._lookahead.select_camera_at_kernel`) copies a view's camera into a
  one-camera array that the projection and SH kernels read
  (:attr:`cdcgs.render.PreparedCamera.on_device`), and the photo is picked from the stacked
  training photos by the same index;
- the Adam rates table (float32 [P, 8]), copied from the host each step (the host advances Adam's
  step counts and the position learning rate as ``FusedAdam.step`` does);
- the slots: one capacity for every view, the largest any view needs
  (:meth:`cdcgs.train.lookahead.Lookahead.capacity`); a view that needs more is captured again.

What does not change between two refinements is fixed in the graph: the Gaussians' tensors, the SH
degree, the render size and whether the step adds densification statistics (the strategy's
:meth:`graph_signature`). When one of them changes the next step captures a new graph. Steps that
refine, views whose count is not known yet and strategies without a signature run as before.

CDC-GS's Γ passes, at refinements, are replayed too: :class:`GammaGroups` captures one group of a
pass's views (binned into slots and measured in one launch) once per pass and replays it for every
group.

The halts of ``--sync-free`` work unchanged: a replayed render notes its count and flags on the
device, and every kernel that changes the training's state reads ``halt``. On the CPU nothing is
captured: the same step runs one operation at a time, and equals the step without ``--cuda-graph``
bit for bit (``tests/test_graph.py``).
"""

from __future__ import annotations

import dataclasses
import gc
import time

import torch
import warp as wp
from torch.autograd.graph import get_gradient_edge, increment_version

from .. import complexity
from .._interop import launch, warp_device, warp_scope, wp_arg
from ..errors import OptionError
from ..kernels._lookahead import select_camera_at_kernel
from ..kernels.adam import adam_quads
from ..kernels.blend import VIEW_TABLE_COLUMNS, VIEW_TABLE_MAP
from ..kernels.projection import Camera
from ..render import ShAdamStep, bin_view, rasterize
from .distributed import my_positions
from .lookahead import READ_EVERY, halt_refusal
from .optim import MAX_LAUNCH_THREADS, FusedAdam, launch_adam

__all__ = ["GammaGroups", "GraphSteps", "capture", "free_earlier_graphs", "graph_refusal", "mark_step_graph"]

# A replayed step of one view on one process applies Adam to the SH coefficients inside their
# adjoint (rasterize's sh_step) instead of writing their gradients for the Adam launch to read back:
# 48 of a degree-3 Gaussian's 59 values. False: every parameter goes through the Adam launch (for
# comparison; the same step, FusedAdam's arithmetic either way).
FUSE_SH_ADAM = True

# Host slots of the per-step copies: the host writes slot (iteration % RING) and queues a copy
# from it; a read of the device (at least every READ_EVERY iterations) waits for every copy, so
# a slot is never rewritten before its copy has run.
RING = 256
assert READ_EVERY < RING


# The tag that an eager step's backward pass puts on each parameter's gradient accumulator (the
# autograd node its graph ends in): the tag lives as long as that node does.
_EARLIER_STEP = "cdcgs.earlier_step"


def mark_step_graph(params) -> None:
    """Tag the gradient accumulators of ``params`` (leaf tensors) that the step's autograd graph
    holds, so that :func:`free_earlier_graphs` knows whether that graph outlives the step."""
    for p in params:
        get_gradient_edge(p).node.metadata[_EARLIER_STEP] = True


def free_earlier_graphs(params) -> bool:
    """Before a capture: free the autograd graph of an earlier step that something still holds, and
    say whether there was one.

    An accumulator of a parameter that outlives its step keeps the CUDA stream it was made on
    (torch's default stream, where the eager steps run), and a captured backward pass that adds
    into it then waits on that stream: the capture fails ("operation would make the legacy stream
    depend on a capturing blocking stream"). What held it on a fresh machine was a reference cycle:
    Warp builds a kernel module on its first launch, and the exceptions its code generation catches
    keep the frames of the calling step, with the step's tensors, until Python's cycle collector
    runs; a full collection (tens of milliseconds) is taken only when a tagged accumulator is found
    alive."""
    if not any(_EARLIER_STEP in get_gradient_edge(p).node.metadata for p in params):
        return False
    gc.collect()
    return True


def graph_refusal(trainer, *, default: bool = False) -> tuple[str, str] | None:
    """Why the steps of ``trainer`` cannot be replayed as CUDA graphs, and what would let them:
    (why, what to change), or None. With ``default`` (the option left at none) a training on the
    CPU is refused too: there the same steps run one operation at a time, for the tests, and gain
    nothing. ``--cuda-graph`` given explicitly raises the reason; left at none the training runs
    without graphs and says why (:meth:`cdcgs.train.trainer.Trainer`)."""
    config = trainer.config
    if default and trainer.device.type != "cuda":
        return "replays steps on CUDA", f"this training runs on {trainer.device.type}"
    if trainer.device.type == "cuda" and not wp.is_mempool_supported(warp_device(trainer.device)):
        return (
            "needs Warp's memory pool on the GPU (the step's sorts and scans allocate inside the capture)",
            "this GPU or driver has none",
        )
    if trainer.device.type == "cuda" and trainer.ranks.distributed and trainer.ranks.backend != "nccl":
        return (
            f"captures the step's all-reduce, which {trainer.ranks.backend} (host memory) cannot take part in",
            "use NCCL, a GPU per process (--dist-backend auto or nccl)",
        )
    refusal = halt_refusal(config, trainer.strategy)
    if refusal is not None:
        return refusal
    if any(getattr(callback, "renders_beside_training", False) for callback in trainer.callbacks):
        return "captures steps, which a viewer's renders on another thread would run into", "drop --view"
    if not isinstance(trainer.optimizer, FusedAdam):
        return "launches FusedAdam itself", "use --optimizer adam or selective"
    world = trainer.ranks.world
    if config.batch_size % world:
        return (
            "captures a step of as many views on every process",
            f"use a --batch-size that {world} processes divide, not {config.batch_size}",
        )
    if config.background == "random":
        return "needs a fixed background", "--background random draws one each step"
    if getattr(trainer.strategy, "graph_signature", None) is None:
        return (
            f"cannot replay the {config.strategy} strategy's steps, whose hooks draw random numbers or read the "
            "device on the host each step",
            "drop --cuda-graph for it",
        )
    sizes = {(c.width, c.height, c.near_plane) for c in trainer.cameras}
    if len(sizes) != 1:
        return (
            f"renders every training view into one image size, and these have {len(sizes)} sizes",
            "drop --cuda-graph for this scene",
        )
    return None


def capture(device: torch.device, body) -> tuple[torch.cuda.CUDAGraph, float, float]:
    """``body()``'s launches (torch's and Warp's) captured as one CUDA graph on ``device``, not run:
    (the graph, the host's wait for the work queued before, the seconds of the capture itself)."""
    waited = time.perf_counter()
    torch.cuda.synchronize(device)  # what torch.cuda.graph does first, timed on its own
    start = time.perf_counter()
    graph = torch.cuda.CUDAGraph()
    # torch's context empties torch's cache first (each capture follows a refinement that
    # replaced the Gaussians): without that, a bonsai training reserved 65.7 GB against 4.7, in
    # the same time. thread_local: CUDA calls of other threads (none of cdcgs's: --view is
    # refused) do not break the capture.
    with torch.cuda.graph(graph, capture_error_mode="thread_local"):
        stream = wp.stream_from_torch(torch.cuda.current_stream(device))
        wp.capture_begin(stream=stream, external=True)
        try:
            body()
        finally:
            wp.capture_end(stream=stream)
    return graph, start - waited, time.perf_counter() - start


def cameras_on_device(cameras: list, device: torch.device) -> wp.array:
    """The :class:`cdcgs.kernels.Camera` of each prepared camera, in one Warp array on ``device``:
    the table a replayed kernel picks a view's camera from (``select_camera_at_kernel``)."""
    return wp.array([c.camera for c in cameras], dtype=Camera, device=warp_device(device))


class GraphSteps:
    """The captured step of one trainer (:class:`cdcgs.train.trainer.Trainer`), and when to take it."""

    fuses_sh_adam = True  # whether _body's render may take the SH coefficients' Adam step (FUSE_SH_ADAM)

    def __init__(self, trainer):
        self.trainer = trainer
        self.device = trainer.device
        self.cuda = self.device.type == "cuda"
        if self.cuda and self.device.index is None:  # "cuda": Warp needs the ordinal
            self.device = torch.device("cuda", torch.cuda.current_device())
        refusal = graph_refusal(trainer)
        if refusal is not None:
            raise OptionError(f"--cuda-graph {refusal[0]}: {refusal[1]}")
        pinned = self.cuda
        # (iteration, view) of each view this process renders, (a signal is pending, a render met
        # NaN), the step's views in batch order: the flags for the all-reduce, the views for
        # --dist-exchange colours
        self.batch = trainer.config.batch_size
        self._flag_entry = 2 * (self.batch // trainer.ranks.world)  # after a pair per view of the process
        self._views_entry = self._flag_entry + 2
        entries = self._views_entry + self.batch
        self.where = torch.zeros(entries, dtype=torch.int32, device=self.device)
        self._where_ring = torch.zeros(RING, entries, dtype=torch.int32, pin_memory=pinned)
        self._where_slots = self._where_ring.numpy()
        self._rates_ring: torch.Tensor | None = None
        self._tables: dict[int, tuple] = {}  # scale -> (cameras on the device, camera of the step, stacked photos)
        self.graph = None
        self.key = None
        self.capacity = 0
        self.captures = 0
        self.freed_graphs = 0  # captures that first freed an earlier step's graph (free_earlier_graphs)
        self.capture_seconds = 0.0  # the host's time in the captures (recording and instantiating)
        # the host's wait, before each capture, for the work queued before it (torch's capture
        # synchronises the device first): on several processes it holds their collectives, so the
        # slowest process's pace; not in capture_seconds
        self.capture_wait_seconds = 0.0
        self.replays = 0
        self.fused_replays = 0  # replays whose SH adjoint took the coefficients' Adam step
        self._table = self._rates = self._grads = None
        self._adam_params: list = []  # the parameters of the Adam launch: self._params less the fused ones
        self._sh_step: ShAdamStep | None = None  # the SH coefficients' step, fused into their adjoint
        self._batch_slots: list = []  # one-camera arrays of the step's views (--dist-exchange colours)

    # ----------------------------------------------------------------------------- when

    def key_of(self, iteration: int, scale: int):
        """What the graph of the step that begins at ``iteration`` is fixed to, or None: take it as
        before. On several processes it is the same on every one (each process's graph holds the
        step's all-reduce, which all must replay together): every part of it is, the addresses
        included, which change only at refinements, where no step is replayed."""
        trainer = self.trainer
        strategy = trainer.strategy
        iterations = range(iteration, iteration + self.batch)
        signature = strategy.graph_signature(iteration)
        if signature is None or any(strategy.refines_at(i) for i in iterations):
            return None
        if any(strategy.graph_signature(i) != signature or trainer._downscale(i) != scale for i in iterations):
            return None
        if sum(adam_quads(p.numel()) for p in trainer.model.params.values()) > MAX_LAUNCH_THREADS:
            return None  # Adam would need several launches (FusedAdam.step splits them)
        # the addresses the graph and Adam's table hold: a refinement or a reset replaces tensors
        optimizer = trainer.optimizer
        addresses = []
        for group in optimizer.param_groups:
            for p in group["params"]:
                state = optimizer.state.get(p, {})
                if "exp_avg" not in state:
                    return None  # Adam's first step makes them
                addresses += [p.data_ptr(), state["exp_avg"].data_ptr(), state["exp_avg_sq"].data_ptr()]
        return (signature, trainer.model.sh_degree, scale, trainer.model.num, trainer.num_gaussians, tuple(addresses))

    def take(self, first: int, views: list[int], backgrounds: list[torch.Tensor]) -> bool:
        """Take the step that begins at iteration ``first`` (a whole batch: ``views`` and
        ``backgrounds``, in batch order) as a replayed step and return True, or return False: the
        trainer takes it as before. On several processes every process decides alike, from what
        all of them know (the counts agreed at the last read), so that they replay together.
        A process renders the batch's positions that :meth:`Trainer.positions` gives it (rank,
        rank + processes, ..., or split by the views' counts): the graph reads each render's
        iteration and view from ``where``, so any split replays; their backgrounds are one colour
        (the graph holds it)."""
        trainer = self.trainer
        ranks = trainer.ranks
        scale = trainer._downscale(first)
        key = self.key_of(first, scale)
        if key != self.key:
            self.release()  # before the refinement or the capture that comes next: not both in memory
        if key is None:
            return False
        lookahead = trainer.lookahead
        agreed = ranks.distributed
        needs = [lookahead.capacity(v, trainer.num_gaussians, scale, agreed=agreed) for v in views]
        if any(needed is None for needed in needs):
            return False  # a first render at this scale reads the count
        if key != self.key or max(needs) > self.capacity:
            self._capture(key, scale, backgrounds[ranks.rank])
        positions = trainer.positions(first, views)
        slot = first % RING
        self._where_slots[slot] = (
            *(value for p in positions for value in (first + p, views[p])),
            trainer.signals.pending is not None,
            trainer._nonfinite_at is not None,
            *views,
        )
        self._rates_slots[slot] = trainer.optimizer.advance(self._params, self.gradient_scale())
        self.where.copy_(self._where_ring[slot], non_blocking=True)
        self._rates.copy_(self._rates_ring[slot], non_blocking=True)
        for p in positions:
            lookahead.replayed(views[p], trainer.num_gaussians, scale, first + p)
        if self.cuda:
            self.graph.replay()
        else:
            self._body()
        for p in self._params:  # Adam wrote through addresses: tell torch, as an in-place op would
            increment_version(p)
        self.replays += 1
        self.fused_replays += self._sh_step is not None
        return True

    # ------------------------------------------------------------------------- capture

    def _capture(self, key, scale: int, background: torch.Tensor) -> None:
        """Capture the step for ``key`` with slots for every view known at this scale."""
        trainer = self.trainer
        lookahead = trainer.lookahead
        agreed = trainer.ranks.distributed
        known = [lookahead.capacity(v, trainer.num_gaussians, scale, agreed) for v in range(len(trainer.scene.train))]
        self.release()  # the old graph's memory goes back before the new one takes its own
        capacity = max(c for c in known if c is not None)
        self.capacity = capacity
        params = [p for group in trainer.optimizer.param_groups for p in group["params"]]
        fused = self._fused_params()
        self._adam_params = [p for p in params if all(p is not f for f in fused)]
        self._params = self._adam_params + fused  # the rates' rows: the Adam launch's first, in its table's order
        count = len(self._params)
        self._rates = torch.zeros(count, 8, dtype=torch.float32, device=self.device)
        self._rates_ring = torch.zeros(RING, count, 8, dtype=torch.float32, pin_memory=self.cuda)
        self._rates_slots = self._rates_ring.numpy()
        self._table = torch.zeros(len(self._adam_params), 7, dtype=torch.int64, device=self.device)
        self._sh_step = None
        if fused:
            state = trainer.optimizer.state
            rows = (len(self._adam_params), len(self._adam_params) + 1)
            moments = [(state[p]["exp_avg"], state[p]["exp_avg_sq"]) for p in fused]
            selective = trainer.config.optimizer == "selective"
            self._sh_step = ShAdamStep(self._rates, rows, moments[0], moments[1], lookahead.halt, selective)
        self._background = background
        self._scale = scale
        self.captures += 1
        trainer.optimizer.zero_grad(set_to_none=True)
        self.freed_graphs += free_earlier_graphs(self._params)
        cameras = self._tables_at(scale)[0]  # Warp allocates them: not inside the capture
        if trainer._exchanges_colours:  # the step's views' cameras, for their SH adjoints
            self._batch_slots = [wp.empty(1, dtype=Camera, device=cameras.device) for _ in range(self.batch)]
        if not self.cuda:
            self.key = key
            return
        graph, waited, seconds = capture(self.device, self._body)
        self.capture_wait_seconds += waited
        self.capture_seconds += seconds
        self._grads = [p.grad for p in self._adam_params]  # the graph's own memory: the table names it
        self._check_gradients()
        self._fill_table()
        trainer.optimizer.zero_grad(set_to_none=True)
        self.graph, self.key = graph, key  # only a capture that succeeded is replayed

    def _tables_at(self, scale: int):
        """(every training view's camera on the device, the one-camera array the kernels read, the
        prepared camera that names it, the training photos stacked) at 1/``scale`` of their size."""
        if scale not in self._tables:
            trainer = self.trainer
            views = range(len(trainer.scene.train))
            pairs = [
                (trainer.cameras[v], trainer.scene.train[v].image) if scale == 1 else trainer._scaled_view(v, scale)
                for v in views
            ]
            cameras = cameras_on_device([c for c, _ in pairs], self.device)
            current = wp.empty(1, dtype=Camera, device=cameras.device)
            prepared = dataclasses.replace(pairs[0][0], on_device=current)
            photos = torch.stack([photo for _, photo in pairs])
            for v, photo in zip(views, photos):  # the views keep their photos in the stack: no second copy
                if scale == 1:
                    trainer.scene.train[v].image = photo
                else:
                    trainer._scaled[(v, scale)] = (pairs[v][0], photo)
            self._tables = {scale: (cameras, current, prepared, photos)}  # one scale at a time
        return self._tables[scale]

    def _body(self) -> None:
        """The step's device work, from ``where`` and the rates table; reads nothing back. As
        :meth:`cdcgs.train.trainer.Trainer.train_step`: each of the process's views rendered and
        back-propagated in turn, the strategy's statistics after the last, the gradients summed
        over the batch (on several processes in the all-reduce), the guard's records, Adam."""
        trainer = self.trainer
        config = trainer.config
        cameras, current, prepared, photos = self._tables_at(self._scale)
        distributed = trainer.ranks.distributed
        lookahead = trainer.lookahead
        if distributed:
            trainer.statistics.begin(trainer.strategy_state, halts=True)
        first = trainer.step + 1
        seen = []  # (loss, PSNR, step context) of each view, as the trainer's step keeps them
        visible = None
        for index, position in enumerate(my_positions(self.batch, trainer.ranks.rank, trainer.ranks.world)):
            pair = self.where[2 * index : 2 * index + 2]  # (iteration, view) of this render
            with warp_scope(self.device):
                launch(
                    select_camera_at_kernel,
                    1,
                    inputs=[cameras, wp_arg(self.where, wp.int32), 2 * index + 1],
                    outputs=[current],
                )
            image, _, info = rasterize(
                **trainer.model.render_args(),
                camera=prepared,
                background=self._background,
                antialiased=config.antialiased,
                capacity=self.capacity,
                sh_step=self._sh_step,
            )
            lookahead.note(info, 0, 0, trainer.model.num, self._scale, where=pair)  # take() records the view
            photo = photos.index_select(0, pair[1:]).squeeze(0)
            # no view index: the signature's hooks read none (every step of the graph shares them);
            # a regularizer's device operations on the Gaussians are captured
            seen.append(trainer._learn(image, photo, info, first + position))
            if config.optimizer == "selective":
                visible = info.visible if visible is None else visible | info.visible
        for _, _, ctx in seen:
            trainer.strategy.observe(ctx, trainer.strategy_state)
        if distributed or self.batch > 1:  # the step's all-reduce and sums, as Trainer.train_step's
            flags = torch.cat([self.where[self._flag_entry : self._views_entry].float(), lookahead.halt.float()])
            cameras = self._batch_cameras(cameras, prepared) if trainer._exchanges_colours else None
            trainer._reduce(self.batch, visible, timed=False, flags=flags if distributed else None, cameras=cameras)
            visible = trainer._visible
        for loss, image_psnr, _ in seen:
            trainer.guard.record(loss, image_psnr, lookahead.halt)
        self._adam(visible, lookahead.halt)

    def _adam(self, visible: torch.Tensor | None, halt: torch.Tensor) -> None:
        """One Adam launch over the parameters of the address table, every one but those whose
        step the SH adjoint took (on the CPU, this step's gradients' table, filled here); nothing
        while ``halt`` is set."""
        threads = sum(adam_quads(p.numel()) for p in self._adam_params)
        if not self.cuda:  # one operation at a time: this step's gradients
            self._check_gradients()
            self._grads = [p.grad for p in self._adam_params]
            self._fill_table()
        launch_adam(self._table, self._rates, threads, visible, halt)
        if not self.cuda:
            self.trainer.optimizer.zero_grad(set_to_none=True)
            self._grads = None

    def gradient_scale(self) -> float:
        """What Adam multiplies the step's gradients by (folded into its rates): the body leaves the
        batch's sums (``Trainer.folds_batch_mean``, which the replayed steps' FusedAdam holds), so
        1 / batch."""
        return 1.0 / self.batch

    def _fused_params(self) -> list:
        """The parameters whose Adam step the SH adjoint applies (``FUSE_SH_ADAM``): the SH
        coefficients of a step of one view on one process (under selective Adam on the view's
        visible Gaussians, the rows the Adam launch's mask selects); else none."""
        trainer = self.trainer
        params = trainer.model.params
        if not (FUSE_SH_ADAM and self.fuses_sh_adam and self.batch == 1 and not trainer.ranks.distributed):
            return []
        if "sh_dc" not in params or "sh_rest" not in params:
            return []
        return [params["sh_dc"], params["sh_rest"]]

    def _check_gradients(self) -> None:
        """After a step's backward pass: a gradient for every parameter of the Adam launch, none for
        those whose step the SH adjoint took (a gradient there came from another part of the loss,
        which the fused step would drop)."""
        names = {id(p): name for name, p in self.trainer.model.params.items()}
        missing = [names.get(id(p), "?") for p in self._adam_params if p.grad is None]
        if missing:
            raise RuntimeError(f"a captured step left {', '.join(missing)} without a gradient")
        extra = [names.get(id(p), "?") for p in self._params[len(self._adam_params) :] if p.grad is not None]
        if extra:
            raise RuntimeError(
                f"a replayed step's loss gives {', '.join(extra)} a gradient besides the render's, which the Adam step "
                "fused into the SH adjoint would drop: set cdcgs.train.graph.FUSE_SH_ADAM = False"
            )

    def _batch_cameras(self, cameras, prepared) -> list:
        """The step's views' cameras on the device, in batch order (``where``'s last entries), as
        prepared cameras like ``prepared`` that the SH adjoint reads."""
        with warp_scope(self.device):
            for position, slot in enumerate(self._batch_slots):
                launch(
                    select_camera_at_kernel,
                    1,
                    inputs=[cameras, wp_arg(self.where, wp.int32), self._views_entry + position],
                    outputs=[slot],
                )
        return [dataclasses.replace(prepared, on_device=slot) for slot in self._batch_slots]

    def _fill_table(self) -> None:
        """Adam's address table: each parameter, its gradient (the graph's), its two moments, its
        first quad, its number of values and its values per row."""
        rows, start = [], 0
        optimizer = self.trainer.optimizer
        for p, grad in zip(self._adam_params, self._grads):
            state = optimizer.state[p]
            addresses = [x.data_ptr() for x in (p, grad, state["exp_avg"], state["exp_avg_sq"])]
            rows.append([*addresses, start, p.numel(), p.numel() // p.shape[0] if p.shape[0] else 1])
            start += adam_quads(p.numel())
        self._table.copy_(torch.tensor(rows, dtype=torch.int64))

    def release(self) -> None:
        """Let go of the graph, its memory (the gradients in its pool) and the tensors it names."""
        self.graph = self.key = None
        self._grads = self._params = self._table = self._sh_step = None
        self._adam_params = []
        self.capacity = 0

    def summary(self) -> dict:
        return {
            "captures": self.captures,
            "replayed_steps": self.replays,
            "capture_seconds": self.capture_seconds,
            "capture_wait_seconds": self.capture_wait_seconds,
            "freed_earlier_graphs": self.freed_graphs,
            "sh_adam_in_adjoint_steps": self.fused_replays,
        }


class GammaGroups:
    """A Γ pass's views (CDC-GS) measured a launch's worth at a time from one CUDA graph.

    Binned one by one, each view of a pass costs the host about 1 ms (a projection, the binning's
    launches and allocations, the Python around them) where the GPU needs 0.4-0.8 ms at 1M
    Gaussians, so the host paced the pass (docs/benchmarks.md). Here a group of views (as many
    as :func:`cdcgs.complexity.complexity_over_views` measures in one launch) is captured once per
    pass: for each of its slots the view's camera picked on the device from ``where``
    (:data:`cdcgs.kernels._lookahead.select_camera_at_kernel`) and its tile lists binned into
    slots (:func:`cdcgs.render.bin_view`), then one ``complexity_views_kernel`` launch into the
    pass's Γ with the views' maps picked by the same indices, and the views' overflow flags copied
    into a table of every view's. The graph is replayed for each group; the last group is filled
    up with its first view (a view measured twice changes no max). The slots are the largest any
    of the pass's views needs; a pass with a view whose count the training does not know runs as
    before. Γ is the same bit for bit. On the CPU nothing is captured: the same body runs for each
    group (``tests/test_graph.py``)."""

    def __init__(self, trainer):
        self.trainer = trainer
        self.device = trainer.graphs.device  # with its ordinal
        self.cuda = self.device.type == "cuda"
        self.captures = 0
        self.capture_seconds = 0.0
        self.groups = 0
        self._cameras = None  # every training view's camera on the device, made once
        self.release()

    def measure(self, indices: list[int], maps, total: torch.Tensor, w_max: str) -> list | None:
        """Measure the views ``indices`` into ``total`` (the exact max; the ``groups`` of
        :func:`cdcgs.complexity.complexity_over_views`): their (index, ``pending_flags``), or None
        when a view's count is unknown (the pass then bins view by view)."""
        trainer = self.trainer
        lookahead = trainer.lookahead
        n = trainer.num_gaussians  # the whole scene's, whose counts the lookahead holds
        needs = [lookahead.capacity(view, n) for view in indices]
        if not indices or any(c is None for c in needs):
            return None
        capacity = max(needs)
        size = complexity.views_per_launch_for(n, capacity)
        groups = [indices[i : i + size] for i in range(0, len(indices), size)]
        groups[-1] = groups[-1] + [groups[-1][0]] * (size - len(groups[-1]))
        self._prepare(size, capacity, maps, indices, total, w_max)
        self._ring = torch.tensor(groups, dtype=torch.int32, pin_memory=self.cuda)
        if self.cuda:
            self._capturing = True
            try:
                self._graph, _, seconds = capture(self.device, self._body)
            finally:
                self._capturing = False
            # the addresses of the graph's own buffers, known once captured; read by every replay
            self._table.copy_(torch.tensor(self._rows, dtype=torch.int64))
            self.captures += 1
            self.capture_seconds += seconds
        for group in range(len(groups)):
            self._where.copy_(self._ring[group], non_blocking=True)
            if self.cuda:
                self._graph.replay()
            else:
                self._body()
        self.groups += len(groups)
        lookahead.gamma_views["within"] += len(indices)
        return [(view, (self._flags[view], self._names)) for view in indices]

    def _prepare(self, size: int, capacity: int, maps, indices: list[int], total: torch.Tensor, w_max: str) -> None:
        """What the body reads or writes that is not made inside it (a capture must not allocate
        what outlives it, nor read host memory that changes)."""
        trainer = self.trainer
        device = self.device
        if self._cameras is None:
            self._cameras = cameras_on_device(trainer.cameras, device)
        self._current = [wp.empty(1, dtype=Camera, device=self._cameras.device) for _ in range(size)]
        self._prepared = [dataclasses.replace(trainer.cameras[0], on_device=c) for c in self._current]
        self._where = torch.zeros(size, dtype=torch.int32, device=device)
        addresses = [0] * len(maps)
        camera = trainer.cameras[0]
        for view in indices:
            hf_map = maps[view]  # the graph reads it through its address: checked here
            if (
                hf_map.shape != (camera.height, camera.width)
                or hf_map.dtype != torch.uint8
                or hf_map.device != device
                or not hf_map.is_contiguous()
            ):
                raise ValueError(
                    f"the complexity map of view {view} must be a contiguous uint8 [{camera.height}, {camera.width}] "
                    f"tensor on {device}, got {hf_map.dtype} {list(hf_map.shape)} on {hf_map.device}"
                )
            addresses[view] = hf_map.data_ptr()
        self._maps = [maps[view] for view in indices]  # their addresses are in the table below
        self._map_addresses = torch.tensor(addresses, dtype=torch.int64).to(device)
        self._flags = torch.zeros(len(maps), len(self._NAMES) + 2, dtype=torch.int32, device=device)
        self._names = tuple(self._NAMES)
        self._table = torch.zeros(size, VIEW_TABLE_COLUMNS, dtype=torch.int64, device=device)
        self._inputs = self.inputs()
        self._size, self._capacity, self._total, self._w_max = size, capacity, total, w_max

    _NAMES = ("means", "quats", "scales", "opacities")  # bin_view's flags of non-finite inputs, in its order

    def _body(self) -> None:
        """One group: each slot's view binned into the slots, the group measured in one launch,
        the views' flags kept. Reads the views from ``where`` only."""
        means, quats, shape = self._inputs
        antialiased = self.trainer.config.antialiased
        infos = []
        with warp_scope(self.device):
            for slot in range(self._size):
                launch(
                    select_camera_at_kernel,
                    1,
                    inputs=[self._cameras, wp_arg(self._where, wp.int32), slot],
                    outputs=[self._current[slot]],
                )
                info = bin_view(
                    means, quats, **shape, camera=self._prepared[slot], antialiased=antialiased, capacity=self._capacity
                )
                if info._pending_names != self._names:  # what the flags table was made for
                    raise RuntimeError(f"bin_view's flags are {info._pending_names}, not {self._names}")
                infos.append(info)
        self._rows, self._held = complexity.views_table_rows(infos, None)  # the maps' column is filled below
        if not self._capturing:  # captured: the table is filled once after the capture (no copy in the graph)
            self._table.copy_(torch.tensor(self._rows, dtype=torch.int64))
        views = self._where.long()
        self._table[:, VIEW_TABLE_MAP] = self._map_addresses.index_select(0, views)
        complexity.launch_complexity_views(self._table, infos[0], self._w_max, self._total)
        self._flags.index_copy_(0, views, torch.stack([info.pending for info in infos]))
        self._infos = infos  # the graph's memory; kept until the pass has read the flags

    def release(self) -> None:
        """Let go of the graph and its memory (after the pass's read of the flags)."""
        self._graph = self._ring = self._where = self._flags = self._table = self._rows = None
        self._capturing = False
        self._infos = self._held = self._inputs = self._total = self._maps = self._map_addresses = None
        self._current = self._prepared = []
        # (means, quats, {"scales", "opacities"}) of the Gaussians the next pass measures: the
        # trainer's own, unless a training on shards sets the gathered scene's for its pass
        self.inputs = self.trainer._bin_inputs

    def summary(self) -> dict:
        return {
            "gamma_captures": self.captures,
            "gamma_capture_seconds": self.capture_seconds,
            "gamma_groups": self.groups,
        }
