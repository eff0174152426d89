"""Training on sharded Gaussians (``--dist-mode shards``): each process of a torchrun launch holds
a slice of the scene, its gradients and its Adam moments, and renders its views of the whole scene
through :func:`cdcgs.train.shards.rasterize_shard`.

What a step does, with W processes and a batch of B views (B >= W):

1. Every process draws the step's B views and backgrounds as data parallelism does (the same
   streams, so the same views), and renders them in rounds of W: in round k process r renders
   position k * W + r of the batch; a process past the batch's end in the last round renders the
   batch's last view again and back-propagates zeros (every process takes part in every exchange).
2. The render sends each view the projection of every slice; its backward pass returns each
   slice's share of the view's gradients to the slice's process, which finishes the projection's
   and the SH evaluation's adjoints. A process's gradients are thus its slice's gradients summed
   over the batch's views, divided by B: the mean over the batch, as data parallelism's
   all-reduce gives it, with nothing all-reduced (with FusedAdam, the division folded into Adam's
   rates: ``gradient_scale``).
3. The densification statistics: the render's ``info`` holds the whole scene's projection into the
   view, so each process adds its views' positional gradients and screen radii into statistics
   over the whole scene (3 floats a Gaussian). At a refinement they are reduced over the
   processes (a sum, or a max for the radii) once, and each process densifies, prunes and resets
   its own slice with its rows of them: 3DGS's decisions are per Gaussian, so the slices together
   take the decisions one process would take. The split children's random draws come from a
   generator seeded by (seed, iteration, rank). The slices' new sizes are then exchanged.
4. Adam steps each slice alone.

CDC-GS's decisions need the whole scene: at a densification step the slices' geometry (11 floats a
Gaussian) is gathered on every process, Γ is measured over it with the training views split over
the processes (reduced as data parallelism's Γ pass reduces them), Ψ over its means, and the
consistency draws come from the step's stream after its own draws, which every process shares:
every process takes the same decisions over the whole scene, and each applies its own rows of them
(CAAT's thresholds, the drawn candidates, the drawn prunes) to its slice.

An evaluation renders the test views in rounds through the sharded render (each process its
share of them, as data parallelism splits them) and scores them as data parallelism does; a
checkpoint and the PLY hold the whole scene (parameters, Adam's moments and the reduced
statistics, gathered a tensor at a time), so a run resumes on any number of processes, sharded
or not. Every ``--check-ranks-every`` iterations the processes compare what they must share (the
step, the view order, the SH degree and the slices' sizes).

On CUDA the steps are replayed as CUDA graphs (:class:`ShardGraphSteps`), as data parallelism's:
rendered into slots sized by the counts every process knows, a halt shared by one all-reduce.

Not yet: CDC-GS's online Γ schedule, caps and targets of the Gaussian count, MCMC, selective
Adam, the resolution schedule, the viewer, and moving Gaussians between slices as they grow apart
(the slices' sizes are in metrics.json). Each is refused with its reason (:func:`shard_refusal`).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import time

import torch
import warp as wp

from .._interop import launch, warp_device, warp_scope, wp_arg
from ..errors import NonFiniteError, OptionError
from ..io import save_checkpoint, write_ply
from ..kernels._lookahead import select_camera_at_kernel
from ..kernels.projection import Camera
from ..render import prepare_camera, start_bin_view
from . import outputs
from .config import TrainConfig, batch_rule
from .distributed import RankDrift, step_seed
from .graph import GraphSteps
from .interrupt import Interrupted
from .model import GaussianModel
from .ops import load_optimizer_state, make_optimizer
from .shards import rasterize_shard
from .strategies import make_strategy
from .strategy import StepContext
from .trainer import TIME_COMMUNICATION_EVERY, Trainer

__all__ = ["ShardedTrainer", "even_rows", "shard_refusal"]

# Logged counts of a refinement that add up over the slices; every other entry is rank 0's.
SUMMED_LOGS = ("cloned", "split", "pruned", "periodic_prune")
# Logged counts of decisions over the whole scene, which every process must take alike.
SHARED_DECISIONS = ("densify_candidates", "prune_candidates", "cdc_densify", "cdc_prune")


def even_rows(count: int, world: int) -> list[int]:
    """``count`` Gaussians split into ``world`` slices in rank order, the first ``count % world``
    one larger."""
    base, extra = divmod(count, world)
    return [base + (rank < extra) for rank in range(world)]


def shard_refusal(config: TrainConfig, world: int, strategy=None) -> str | None:
    """Why ``--dist-mode shards`` cannot train ``config`` on ``world`` processes (with
    ``strategy``, once it is built), or None."""
    if world < 2:
        return "--dist-mode shards splits the Gaussians over the processes of a torchrun launch: launch two or more"
    if config.optimizer == "selective":
        return "--optimizer selective is not built for --dist-mode shards: use adam or torch-adam"
    if config.resolution_schedule not in (None, "none"):
        return f"--resolution-schedule {config.resolution_schedule} is not built for --dist-mode shards yet: use none"
    if config.dist_exchange != "gradients" or config.dist_balance != "none":
        return (
            "--dist-exchange and --dist-balance are data parallelism's: --dist-mode shards exchanges the projected "
            "slices"
        )
    if strategy is None:
        return None
    name = config.strategy
    if not hasattr(strategy, "grad_threshold"):
        return (
            f"--strategy {name} relocates Gaussians over the whole scene; --dist-mode shards trains 3DGS-style "
            "strategies"
        )
    if getattr(strategy, "needs_complexity", False) and getattr(strategy, "complexity_schedule", "full") != "full":
        return (
            "--complexity-schedule online adds each training render to Γ over this process's Gaussians, which "
            "--dist-mode shards does not do yet: use the full schedule"
        )
    caps = [
        f"--{option.replace('_', '-')}"
        for option in ("max_gaussians", "target_gaussians")
        if getattr(strategy, option, None) is not None
    ]
    if getattr(strategy, "budget_schedule", "none") != "none":
        caps.append("--budget-schedule")
    if caps:
        return f"{', '.join(caps)} caps the whole scene's count, which --dist-mode shards does not rank yet"
    return None


class ShardGraphSteps(GraphSteps):
    """The replayed steps of a training on shards: as data parallelism's
    (:class:`cdcgs.train.graph.GraphSteps`: the host writes each step's iterations and views into
    ``where`` and Adam's rates, then replays), where each round renders through
    :func:`cdcgs.train.shards.rasterize_shard` with slots. A round's cameras (every process's
    view) are picked on the device from the step's views in ``where``, the exchanges (NCCL's
    point-to-point transfers, forward and in the backward pass) are captured with the kernels, and
    one all-reduce of the halt replaces data parallelism's all-reduce of the gradients. Whether a
    step is replayed or taken eagerly, it takes the same collectives in the same order (each round's
    transfers forward and back, then the halt's all-reduce), and every process renders into slots
    or reads its count alike (both from the counts agreed at the last read), so a process that
    captures again (its own tensors moved) while another replays waits for nothing it lacks."""

    fuses_sh_adam = False  # its render is the shard's, which takes no SH step

    def __init__(self, trainer):
        super().__init__(trainer)
        # one camera slot per process: a round renders every process's view of it
        self._round_slots = [
            wp.empty(1, dtype=Camera, device=warp_device(self.device)) for _ in range(trainer.ranks.world)
        ]

    def key_of(self, iteration: int, scale: int):
        key = super().key_of(iteration, scale)
        return None if key is None else (*key, tuple(self.trainer.rows))  # the exchanges' sizes

    def _body(self) -> None:
        """The step's device work: in round k process r renders position k * W + r of the batch
        (its iteration and view in ``where``), every process's camera of the round picked from the
        step's views; then the halt shared, the statistics, the guard's records and Adam on this
        slice (of the batch's mean: ``gradient_scale``)."""
        trainer = self.trainer
        cameras, _, prepared, photos = self._tables_at(self._scale)
        lookahead = trainer.lookahead
        rank, world = trainer.ranks.rank, trainer.ranks.world
        round_cameras = [dataclasses.replace(prepared, on_device=slot) for slot in self._round_slots]
        first = trainer.step + 1
        seen = []
        for index in range(self.batch // world):
            with warp_scope(self.device):
                for r, slot in enumerate(self._round_slots):
                    entry = self._views_entry + index * world + r
                    launch(
                        select_camera_at_kernel,
                        1,
                        inputs=[cameras, wp_arg(self.where, wp.int32), entry],
                        outputs=[slot],
                    )
            image, _, info = rasterize_shard(
                **trainer.model.render_args(),
                cameras=round_cameras,
                rows=trainer.rows,
                background=self._background,
                antialiased=trainer.config.antialiased,
                capacity=self.capacity,
            )
            pair = self.where[2 * index : 2 * index + 2]  # (iteration, view) of this process's render
            lookahead.note(info, 0, 0, trainer.num_gaussians, self._scale, where=pair)
            photo = photos.index_select(0, pair[1:]).squeeze(0)
            seen.append(trainer._learn(image, photo, info, first + index * world + rank))
        halt = trainer._share_halt()
        for _, _, ctx in seen:
            trainer.strategy.observe(ctx, trainer.strategy_state)
        for loss, image_psnr, _ in seen:
            trainer.guard.record(loss, image_psnr, halt)
        self._adam(None, halt)  # of the gradients' mean over the batch: gradient_scale


# NCCL registers the buffers of a captured graph's transfers unless told not to: with the sharded
# render's point-to-point transfers that made the capture fail on H100s ("operation would make the
# legacy stream depend on a capturing blocking stream"), its peer left waiting inside the transfer.
# A training on shards turns it off unless the launch sets it (ShardedTrainer.run).
GRAPH_REGISTER = "NCCL_GRAPH_REGISTER"


class _Scene:
    """What a strategy's ``initialize_state`` reads of a model, for statistics over the whole scene."""

    def __init__(self, num: int, device: torch.device):
        self.num, self.device = num, device


class ShardedTrainer(Trainer):
    """:class:`cdcgs.train.trainer.Trainer` with the Gaussians split over the processes (module
    docstring). ``Trainer(config)`` makes one when ``config.dist_mode`` is "shards"."""

    dist_mode = "shards"
    replicated = False
    graph_steps = ShardGraphSteps

    # ----------------------------------------------------------------------------- set-up

    def run(self) -> dict:
        """As :meth:`Trainer.run`, with NCCL's registration of captured buffers off (unless the
        environment sets it): read when the process group's communicator starts."""
        os.environ.setdefault(GRAPH_REGISTER, "0")
        return super().run()

    def _graph_steps(self):
        registers = os.environ.get(GRAPH_REGISTER, "0")
        if self.device.type == "cuda" and registers != "0" and self.config.cuda_graph is not False:
            why = (
                f"--cuda-graph captures the sharded render's NCCL transfers, which fails where NCCL registers a "
                f"captured graph's buffers ({GRAPH_REGISTER}={registers}): unset it or set it to 0"
            )
            if self.config.cuda_graph:
                raise OptionError(why)
            self.graph_off = why
            if self.ranks.is_main:
                print(f"steps run without CUDA graphs: {why}")
            return None
        return super()._graph_steps()

    def _setup(self):
        config = self.config
        refusal = shard_refusal(config, self.ranks.world)
        if refusal is None and self.ranks.backend == "gloo" and torch.device(self.device).type == "cuda":
            refusal = (
                "--dist-mode shards exchanges the slices on the GPUs with NCCL; gloo takes CPU tensors: use a GPU "
                "per process (--device auto) or --device cpu"
            )
        if refusal is None:  # the command's strategy (a resumed run's is checked once its checkpoint is read)
            refusal = shard_refusal(config, self.ranks.world, make_strategy(config.strategy, self.strategy_options))
        if refusal is not None:  # before the scene loads
            raise OptionError(refusal)
        self.rows = None  # set by a resumed run's checkpoint (_restore_gaussians)
        super()._setup()
        refusal = shard_refusal(self.config, self.ranks.world, self.strategy)
        if refusal is None and any(getattr(c, "renders_beside_training", False) for c in self.callbacks):
            refusal = "--view renders the model of one process, which holds a slice under --dist-mode shards"
        sizes = {(camera.width, camera.height) for camera in self.cameras}
        sizes |= {(view.width, view.height) for view in self.scene.test}
        if refusal is None and len(sizes) > 1:
            refusal = (
                "--dist-mode shards renders the processes' views of a step together, at one image size; this scene "
                f"has {len(sizes)}"
            )
        if refusal is not None:
            raise OptionError(refusal)
        self.statistics = None  # data parallelism's per-step exchange of the statistics
        if self.rows is None:  # a new run: the initial Gaussians split evenly
            whole = self.model
            self.rows = even_rows(whole.num, self.ranks.world)
            start, end = self._span()
            self.model = GaussianModel(
                {name: p.detach()[start:end].clone() for name, p in whole.params.items()},
                max_sh_degree=whole.max_sh_degree,
                sh_degree=whole.sh_degree,
            )
            self.optimizer = make_optimizer(
                self.model, self.config.lr, self.scene.extent, self.config.optimizer, batch_rule(self.config)
            )
            del whole
        elif not self.ranks.is_main:
            # A resumed run's statistics are summed over the processes already: rank 0 keeps them,
            # the others add to zeros.
            for key, kind in self.strategy.statistics().items():
                if kind == "sum":
                    self.strategy_state[key] = torch.zeros_like(self.strategy_state[key])
        self._config_json["rows"] = list(self.rows)

    def _restore_gaussians(self, state: dict) -> None:
        """This process's slice of a checkpoint's Gaussians and Adam moments, cut on the CPU: the
        slices the checkpoint records where they fit this launch, else even ones."""
        params = state["model"]["params"]
        total = params["means"].shape[0]
        saved = state.get("rows")
        fits = isinstance(saved, list) and len(saved) == self.ranks.world and sum(saved) == total
        self.rows = list(saved) if fits else even_rows(total, self.ranks.world)
        start, end = self._span()
        self.model = GaussianModel(
            {name: value[start:end].to(self.device) for name, value in params.items()},
            max_sh_degree=state["model"]["max_sh_degree"],
            sh_degree=state["model"]["sh_degree"],
        )
        self.optimizer = make_optimizer(self.model, self.config.lr, self.scene.extent, self.config.optimizer)
        moments = state["optimizer"]
        load_optimizer_state(
            self.optimizer,
            {
                **moments,
                "state": {
                    index: {
                        key: value[start:end] if key in ("exp_avg", "exp_avg_sq") else value
                        for key, value in each.items()
                    }
                    for index, each in moments["state"].items()
                },
            },
        )

    def _span(self) -> tuple[int, int]:
        """[start, end) of this process's slice in the whole scene."""
        start = sum(self.rows[: self.ranks.rank])
        return start, start + self.rows[self.ranks.rank]

    @property
    def num_gaussians(self) -> int:
        return sum(self.rows)

    # ------------------------------------------------------------------------------- step

    def train_step(self) -> dict:
        """One step of ``--batch-size`` views over the processes (module docstring)."""
        config = self.config
        rank, world = self.ranks.rank, self.ranks.world
        first = self.step + 1
        count = min(config.batch_size, config.iters - self.step)
        last = self.step + count
        # One step in TIME_COMMUNICATION_EVERY (the one data parallelism times) is timed: its
        # exchanges wait for the device and the other processes around them.
        timed = (first // config.batch_size) % TIME_COMMUNICATION_EVERY == 10
        timer = [0.0, 0.0] if timed else None  # [wait, transfer] seconds of the step's exchanges
        lookahead = self.lookahead
        if lookahead is not None:
            self._snapshots[first] = self._host_state()
        if timed:
            self._synchronize()
            step_start = time.perf_counter()
        views, backgrounds = self._start_step(first, last)
        if self._replayed(first, last, views, backgrounds, timed):
            return {}
        whole = self.num_gaussians
        seen = []
        for round_start in range(0, count, world):
            positions = [min(round_start + r, count - 1) for r in range(world)]
            position = positions[rank]
            cameras = [self.cameras[views[p]] for p in positions]
            capacity = self._round_capacity([views[p] for p in positions])
            try:
                image, _, info = rasterize_shard(
                    **self.model.render_args(),
                    cameras=cameras,
                    rows=self.rows,
                    background=backgrounds[position],
                    antialiased=config.antialiased,
                    capacity=capacity,
                    exchange_timer=timer,
                )
            except NonFiniteError:  # raised on every process at once (a render that reads its count)
                self._settle_in_step()  # unless an earlier iteration halted: then it is taken again
                self._nonfinite_at = first + position
                raise self._nonfinite_error() from None
            if lookahead is not None and capacity is None:
                lookahead.counted(views[position], info.num_intersections, whole, 1, first + position)
            elif lookahead is not None:  # an overflow or NaN halts every process (below)
                lookahead.note(info, first + position, views[position], whole)
            if round_start + rank >= count:  # past the batch: its part of the exchanges, with zeros
                (image.sum() * 0.0).backward()
                continue
            view_index = views[position]
            seen.append(self._learn(image, self.scene.train[view_index].image, info, first + position, view_index))
        halt = self._share_halt()
        for _, _, ctx in seen:
            self.strategy.observe(ctx, self.strategy_state)
        # The step's stream after its draws (its backgrounds), the same on every process: the
        # whole scene's draws of its refinements (CDC-GS's) come from it, as one process's would.
        if any(self.strategy.refines_at(iteration) for iteration in range(first, last + 1)):
            self._scene_generator = torch.Generator(device=self.device)
            self._scene_generator.set_state(self.generator.get_state())
        # Adam steps the mean over the batch's views of the gradients' sum: FusedAdam with the
        # division folded into its rates (as the replayed steps), another Adam after a division.
        adam = {} if halt is None else {"halt": halt}
        if self.folds_batch_mean:
            adam["gradient_scale"] = 1.0 / count
        elif count != 1:
            for group in self.optimizer.param_groups:
                p = group["params"][0]
                if p.grad is not None:
                    p.grad.div_(count)
        for loss, image_psnr, _ in seen:
            self.guard.record(loss, image_psnr, halt)
        self.step = last
        self.step_events = []
        for iteration in range(first, last + 1):
            if self.strategy.refines_at(iteration):
                self._settle_in_step()  # a refinement reads the Gaussians: no halted iteration before it
                self.check_numbers(params=True)
                self._synchronize()  # the step's kernels are not the refinement's time
                began = time.perf_counter()
                log = self._refine(iteration)
                if log:
                    self._synchronize()
                    log["refine_seconds"] = time.perf_counter() - began
                    self.step_events.append((iteration, log))
        self.optimizer.step(**adam)
        self.optimizer.zero_grad(set_to_none=True)
        self.strategy.after_step(self._context(last), self.strategy_state)
        if timed:
            self._synchronize()
            step_ms = (time.perf_counter() - step_start) * 1e3
            # each round: this slice's 12 numbers a Gaussian (48 bytes) to the other views and back
            # 10 (40 bytes), and the other slices' for this process's view
            mine, total = self.rows[rank], sum(self.rows)
            moved = -(-count // world) * ((world - 1) * mine + (total - mine)) * (48 + 40)
            self._communication.append((timer[0] * 1e3, timer[1] * 1e3, step_ms, moved))
        merged = {}
        for _, log in self.step_events:
            merged.update(log)
        return merged

    def _round_capacity(self, views: list[int]) -> int | None:
        """The slots of a round whose processes render ``views`` (with ``--sync-free`` and the
        replayed steps): the most any of them needs by the counts every process knows alike, or
        None where one is unknown (every process then reads its view's count: all pass a capacity
        or none)."""
        if self.lookahead is None:
            return None
        needs = [self.lookahead.capacity(view, self.num_gaussians, agreed=True) for view in views]
        return None if any(need is None for need in needs) else max(needs)

    def _share_halt(self) -> torch.Tensor | None:
        """After a step's renders: any process's halt (a render that overflowed its slots or met
        NaN) becomes every process's, before the statistics, the guard and Adam read it (one
        all-reduce of one number; a step taken again must add nothing twice on any process)."""
        if self.lookahead is None:
            return None
        return self.ranks.all_reduce_(self.lookahead.halt, "max")

    def _prime_counts(self) -> None:
        """Every training view's count of (tile, Gaussian) pairs for the whole scene before the
        first step: each process bins its slice into every view, and the counts (which add up over
        the Gaussians) are summed over the processes. Every process then knows them alike, so the
        first steps can take slots."""
        lookahead = self.lookahead
        if lookahead is None or self.step >= self.config.iters:
            return
        model = self.model
        counts = torch.zeros(len(self.cameras), dtype=torch.int64, device=self.device)
        if model.num:  # an empty slice adds nothing (and cannot be binned)
            with torch.no_grad():
                shape = {"scales": model.scales(), "opacities": model.opacities()}
                means, quats = model.params["means"].detach(), model.params["quats"].detach()
                for view, camera in enumerate(self.cameras):
                    pending = start_bin_view(means, quats, **shape, camera=camera, antialiased=self.config.antialiased)
                    counts[view] = pending.count_on_device[0]
        values = self.ranks.all_reduce_(counts, "sum").tolist()
        lookahead.prime(values, self.num_gaussians, 1, self.step)
        lookahead.merge([lookahead.known()])  # the same on every process: agreed

    def _refine(self, iteration: int) -> dict:
        """The strategy's refinement of ``iteration`` on this process's slice, with its rows of
        the statistics reduced over the processes; the slices' new sizes exchanged. Returns the
        refinement's log with the counts added up over the slices."""
        rank = self.ranks.rank
        kinds = self.strategy.statistics()
        whole = self.strategy_state
        reduced = {key: self.ranks.all_reduce_(whole[key].clone(), kind) for key, kind in kinds.items()}
        start, end = self._span()
        rows_of_mine = {key: reduced[key][start:end] for key in kinds}
        mine = {**{key: value for key, value in whole.items() if key not in kinds}, **rows_of_mine}
        # The split children's draws: this slice's own stream, the same in a resumed run.
        self.generator.manual_seed(step_seed(step_seed(self.config.seed, iteration) & 0x7FFFFFFF, rank))
        log = self.strategy.refine(self._context(iteration), mine)
        restarted = any(mine[key] is not rows_of_mine[key] for key in kinds)  # the strategy began them anew
        self.rows = [int(n) for n in self.ranks.all_gather_object(self.model.num)]
        logs = self.ranks.all_gather_object(log)
        decided = [{key: each.get(key) for key in SHARED_DECISIONS} for each in logs]
        if any(each != decided[0] for each in decided):
            raise RankDrift(
                f"at iteration {iteration} the processes took different decisions over the whole scene ({decided}): "
                "the sharded run is no longer one run; its last checkpoint is the last good state"
            )
        if any(self.ranks.all_gather_object(restarted)):
            self.strategy_state = {**whole, **self.strategy.initialize_state(_Scene(sum(self.rows), self.device))}
        if not log:
            return {}
        merged = dict(logs[0])
        for key in SUMMED_LOGS:
            if any(key in each for each in logs):
                merged[key] = sum(each.get(key, 0) for each in logs)
        if "gaussians" in merged:
            merged["gaussians"] = sum(self.rows)
        return merged

    def _context(self, iteration: int, info=None, view_index: int | None = None) -> StepContext:
        ctx = super()._context(iteration, info, view_index)
        if info is None:  # a refinement's: decisions over the whole scene are taken there
            ctx.whole_scene = lambda: self._whole_context(iteration)
        return ctx

    def _whole_context(self, iteration: int) -> tuple[StepContext, slice]:
        """(a refinement's context over the whole scene, this slice's rows in it): the slices'
        geometry gathered on every process (11 floats a Gaussian, no colours), its training views
        binned from it, the processes' ranks (a Γ pass splits its views over them) and the step's
        shared stream of random numbers."""
        geometry = {
            name: self._gather(self.model.params[name].detach())
            for name in ("means", "log_scales", "quats", "opacity_logits")
        }
        count = geometry["means"].shape[0]
        geometry["sh_dc"] = geometry["means"].new_zeros(count, 1, 3)
        geometry["sh_rest"] = geometry["means"].new_zeros(count, 0, 3)
        whole = GaussianModel(geometry, max_sh_degree=0)
        with torch.no_grad():
            shape = {"scales": whole.scales(), "opacities": whole.opacities()}
        means, quats = whole.params["means"].detach(), whole.params["quats"].detach()
        antialiased = self.config.antialiased

        def bins(view_index: int, counted: bool = False):
            return start_bin_view(means, quats, **shape, camera=self.cameras[view_index], antialiased=antialiased)

        groups = self.gamma_groups  # a Γ pass's groups of views replayed, over the gathered scene
        if groups is not None:
            groups.inputs = lambda: (means, quats, shape)

        ctx = StepContext(
            step=iteration,
            total_steps=self.config.iters,
            model=whole,
            optimizer=None,
            info=None,
            view_index=None,
            extent=self.scene.extent,
            generator=self._scene_generator,
            bins=bins,
            gamma_groups=groups,
            views=self.scene.train,
            complexity_maps=self.complexity_maps,
            ranks=self.ranks,
        )
        start, end = self._span()
        return ctx, slice(start, end)

    # --------------------------------------------------------------------- checks and signals

    def _check_ranks(self, step: int) -> None:
        """The processes hold different slices; what they must share is compared instead."""
        mine = (self.step, list(self.rows), self.model.sh_degree, list(self.view_queue))
        shared = self.ranks.all_gather_object(mine)
        if any(each != shared[0] for each in shared):
            raise RankDrift(
                f"at iteration {step} the processes disagree on the step, the slices' sizes, the SH degree or the "
                f"view order ({[each[:3] for each in shared]}): the sharded run is no longer one run; its last "
                "checkpoint is the last good state"
            )

    def _raise_pending(self, agreed: bool = True) -> None:
        """Stop cleanly where a signal is pending on any process, at an ``agreed`` point (the
        processes exchange whether one is, there: no step carries an all-reduce to hold it)."""
        if not agreed:
            return
        pending = self.ranks.all_gather_object(self.signals.pending is not None)
        if any(pending):
            raise Interrupted(self.signals.pending or signal.SIGTERM, clean=True)

    # ------------------------------------------------------------------ the whole scene

    def _gather(self, tensor: torch.Tensor, device=None, everywhere: bool = True) -> torch.Tensor | None:
        """This slice's rows of a per-Gaussian ``tensor`` gathered with every other slice's into
        the whole scene's (every process takes part), on ``device`` (the tensor's by default); with
        ``everywhere`` False only rank 0 keeps it (the others get None)."""
        most = max(self.rows)
        padded = tensor.new_zeros((most, *tensor.shape[1:]))
        padded[: tensor.shape[0]] = tensor
        parts = self.ranks.all_gather_(padded)
        del padded
        if not (everywhere or self.ranks.is_main):
            return None
        device = tensor.device if device is None else device
        return torch.cat([parts[r, :rows].to(device) for r, rows in enumerate(self.rows)])

    def whole_model(self, device=None, everywhere: bool = True) -> GaussianModel | None:
        """The whole scene's Gaussians, gathered from the slices (a collective): on every process,
        or with ``everywhere`` False on rank 0 only (None on the others)."""
        params = {name: self._gather(p.detach(), device, everywhere) for name, p in self.model.params.items()}
        if not (everywhere or self.ranks.is_main):
            return None
        return GaussianModel(params, max_sh_degree=self.model.max_sh_degree, sh_degree=self.model.sh_degree)

    def _evaluate(self, final: bool, render_round=None) -> dict:
        """The test views rendered in rounds through the sharded render (each process its share,
        the others sending their slices' projections), scored as data parallelism scores them:
        no process holds more of the scene than a training step does."""
        cameras = {}

        def render_round(round_views):
            present = [view for view in round_views if view is not None]
            for view in present:
                if id(view) not in cameras:
                    cameras[id(view)] = prepare_camera(view.viewmat, view.K, view.width, view.height)
            # a process past the views' end renders the round's last view again, and drops it
            picked = [cameras[id(view if view is not None else present[-1])] for view in round_views]
            image, _, _ = rasterize_shard(
                **self.model.render_args(),
                cameras=picked,
                rows=self.rows,
                background=self.background,
                antialiased=self.config.antialiased,
            )
            return image if round_views[self.ranks.rank] is not None else None

        return super()._evaluate(final, render_round=render_round)

    def state_dict(self) -> dict | None:
        """The whole scene's checkpoint on rank 0, as one process's would be (every process takes
        part; the others get None): the slices' parameters and Adam moments gathered onto the CPU
        a tensor at a time, the statistics reduced over the processes."""
        state = super().state_dict()
        cpu = torch.device("cpu")
        model = self.whole_model(cpu, everywhere=False)
        optimizer = state["optimizer"]
        moments = {}
        for index in sorted(optimizer["state"]):  # the same order on every process
            moments[index] = {
                key: self._gather(value, cpu, everywhere=False) if key in ("exp_avg", "exp_avg_sq") else value
                for key, value in optimizer["state"][index].items()
            }
        kinds = self.strategy.statistics()
        statistics = {
            key: self.ranks.all_reduce_(self.strategy_state[key].clone(), kind) for key, kind in kinds.items()
        }
        if not self.ranks.is_main:
            return None
        state["model"] = model.state_dict()
        optimizer["state"] = moments
        state["strategy_state"] = {
            key: statistics[key].to(cpu) if key in kinds else value for key, value in self.strategy_state.items()
        }
        state["rows"] = list(self.rows)
        return state

    def save(self, ply: bool = True) -> None:
        """The checkpoint (and the PLY) of the whole scene, written by rank 0 after every process
        has given its slice. The first signal cuts neither the gathering nor the writes."""
        if self.lookahead is not None:
            self._settle()  # a halted iteration: the state before it is the one to write
        self.check_numbers(params=True)
        with self.signals.deferred():
            state = self.state_dict()
            if self.ranks.is_main:
                save_checkpoint(self.checkpoint_path, state)
                if ply:
                    whole = GaussianModel.from_state_dict(state["model"])
                    write_ply(os.path.join(self.out, outputs.PLY), whole.to_ply())
            self.saved_step = self.step

    def _communication_summary(self) -> dict:
        """As data parallelism's, where the exchanges are the sharded render's: its
        ``all_reduce_*`` entries hold their transfers (forward and backward, in every round of the
        timed step) and the bytes this process sent and received, ``wait_ms_per_step`` the waits for
        the other processes before each."""
        summary = super()._communication_summary()
        if summary["timed_steps"]:
            summary["exchanged_by"] = "the sharded render's point-to-point transfers"
        return summary

    def _result_extras(self) -> dict:
        return {"dist_mode": "shards", "rows": list(self.rows)}
