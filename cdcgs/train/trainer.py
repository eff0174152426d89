"""The 3DGS training loop: data, model, optimizer, strategy, evaluation, outputs, resume.

The :class:`Trainer` owns every piece of mutable state of a run: the model, the optimizer, the
strategy's state, the random generators, the view order, the complexity-map cache, the history.
All of it goes into the checkpoint and comes back on resume.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import time
import traceback
import typing
import weakref

import torch

from .._interop import warp_device
from ..complexity import ComplexityMaps
from ..errors import InputError, NonFiniteError, OptionError
from ..io import load_checkpoint, load_scene, save_checkpoint, write_ply
from ..io.checkpoint import remove_temporary_files
from ..render import bin_view, prepare_camera, rasterize, sh_adjoint, start_bin_view
from . import outputs
from .config import TrainConfig, background_color, batch_rule, config_to_dict, resolve_defaults
from .distributed import (
    RankDrift,
    RankFailed,
    Ranks,
    StatisticsSync,
    _environment,
    balanced_positions,
    my_positions,
    rank_device,
    splits_by_counts,
    step_seed,
)
from .evaluate import evaluate, lpips_metric
from .graph import GammaGroups, GraphSteps, graph_refusal, mark_step_graph
from .guard import NumericGuard, TrainingDiverged
from .interrupt import Interrupted, StopSignals
from .lookahead import READ_EVERY, Halted, Lookahead, halt_refusal
from .loss import fused_photometric_loss, mse_to_psnr, photometric_loss, psnr
from .model import GaussianModel
from .ops import load_optimizer_state, make_optimizer, set_hyperparameters
from .optim import FusedAdam
from .schedules import dash_schedule, position_lr
from .strategies import make_strategy
from .strategy import StepContext

__all__ = ["CHECKPOINT_FORMAT", "Interrupted", "Trainer", "TrainingDiverged", "crossed", "resolve_device"]

log = logging.getLogger("cdcgs")

# Version of the checkpoint layout. 1: written before the restructure (global RNG states, the
# viewer's options in the configuration, `adc`); 2: the trainer's generators only.
CHECKPOINT_FORMAT = 2


def resolve_device(name: str) -> torch.device:
    """The torch device of a ``--device`` option (``auto``: CUDA when there is one)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise OptionError(f"device {name!r} is not a torch device (cuda, cuda:0, cpu, auto)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise OptionError(f"device {name!r} asked for, but torch sees no CUDA GPU")
    if device.type not in ("cuda", "cpu"):
        raise OptionError(f"device {name!r}: cdcgs runs on cpu or cuda")
    return device


def crossed(before: int, after: int, every: int) -> bool:
    """Whether a step from iteration ``before`` to ``after`` passes a multiple of ``every`` (0:
    never): the events counted in iterations (views seen) fire in the step that reaches them."""
    return every > 0 and after // every > before // every


# How often the data-parallel step times its all-reduce (a synchronisation before and after it):
# one step in this many, for metrics.json's communication share. A timed step runs eagerly, not
# replayed: on 4 × H200 (2026-11-27) one took 11.8 ms against 3.8 ms replayed, so one in 50 cost
# about 3.5% of a 2-GPU bonsai training; one in 250 still times 60 steps of 15,000.
TIME_COMMUNICATION_EVERY = 250


def _upgrade_checkpoint(state: dict, path: str) -> dict:
    """A checkpoint of an earlier layout in today's, or InputError when it cannot be."""
    version = state.get("format", 1)
    if version > CHECKPOINT_FORMAT:
        raise InputError(
            path,
            f"written by a newer cdcgs (checkpoint format {version}; this version reads up to {CHECKPOINT_FORMAT})",
        )
    missing = [
        key
        for key in ("model", "optimizer", "strategy_state", "step", "generator", "view_generator")
        if key not in state
    ]
    if missing:
        raise InputError(path, f"not a cdcgs training checkpoint (no {', '.join(missing)})")
    nonfinite = [f"model {name}" for name, value in state["model"]["params"].items() if not torch.isfinite(value).all()]
    for group_state in state["optimizer"].get("state", {}).values():
        for key, value in group_state.items():
            if torch.is_tensor(value) and value.is_floating_point() and not torch.isfinite(value).all():
                nonfinite.append(f"optimizer {key}")
    if nonfinite:
        raise InputError(
            path, f"holds NaN or infinite values ({', '.join(sorted(set(nonfinite)))}): it cannot be resumed"
        )
    if version == 1:
        state = dict(state)
        state.pop("rng", None)  # global generator states: nothing draws from them any more
        options = dict(state.get("strategy_options", {}))
        options.pop("save_maps", None)  # a training option now (--save-maps)
        state["strategy_options"] = options
        state["format"] = CHECKPOINT_FORMAT
    return state


def _check_batch(batch_size: int, world: int) -> None:
    if world > batch_size:
        raise OptionError(
            f"--batch-size {batch_size} is smaller than the {world} processes: each "
            f"renders at least one view per step (use --batch-size {world} or more)"
        )


def refinement_seconds(events: list[dict]) -> dict:
    """Wall-clock seconds of the training spent in the strategy's refinements (densification,
    pruning, resets, relocation) and, for CDC-GS, in its Γ passes and density (KNN) of them, summed
    over the logged refinements (each timed with the device synchronised at both ends)."""
    return {
        "refine_seconds": sum(e.get("refine_seconds", 0.0) for e in events),
        "gamma_seconds": sum(e.get("gamma_seconds", 0.0) for e in events),
        "psi_seconds": sum(e.get("psi_seconds", 0.0) for e in events),
    }


def held_memory(device: torch.device, peak_reserved: int) -> dict:
    """What the process held of the GPU besides the tensors it used (``peak_gpu_memory_gb``):
    ``peak_gpu_memory_reserved_gb``, the most torch's caching allocator kept over training and
    evaluations (freed blocks it holds for reuse included); ``warp_mempool_peak_gb``, the most
    Warp's own allocations used at once (its sorts' scratch space); ``gpu_memory_in_use_gb``, the
    device's memory in use when the run ends (after the final evaluation), every process on the GPU
    and the CUDA contexts included (what nvidia-smi shows). None on the CPU."""
    if device.type != "cuda":
        return {"peak_gpu_memory_reserved_gb": None, "warp_mempool_peak_gb": None, "gpu_memory_in_use_gb": None}
    import warp as wp

    wp_device = warp_device(device)
    pool = wp.get_mempool_used_mem_high(wp_device) if wp.is_mempool_enabled(wp_device) else 0
    free, total = torch.cuda.mem_get_info(device)
    return {
        "peak_gpu_memory_reserved_gb": peak_reserved / 1e9,
        "warp_mempool_peak_gb": pool / 1e9,
        "gpu_memory_in_use_gb": (total - free) / 1e9,
    }


def allocator_now(device: torch.device) -> dict:
    """torch's caching allocator at this moment on a CUDA ``device``: ``gpu_memory_reserved_gb``
    (what it holds, freed blocks kept for reuse included) and ``gpu_memory_allocated_gb`` (its
    live tensors); empty on the CPU. Host counters: no synchronisation. The history's
    ``gpu_memory`` timeline and its evaluations carry them, to show when the cache grows."""
    if device.type != "cuda":
        return {}
    return {
        "gpu_memory_reserved_gb": torch.cuda.memory_reserved(device) / 1e9,
        "gpu_memory_allocated_gb": torch.cuda.memory_allocated(device) / 1e9,
    }


def mean_communication(summaries: list[dict], backend: str | None) -> dict:
    """metrics.json's ``communication``: the processes' timings (:meth:`Trainer._communication_summary`)
    averaged, with the shares of the timed step, the all-reduce's rate, and each process's own."""
    if not all(s.get("timed_steps") for s in summaries):
        return {"timed_steps": 0, "backend": backend}
    keys = ("wait_ms_per_step", "all_reduce_ms_per_step", "all_reduce_bytes_per_step", "step_ms")
    mean = {k: sum(s[k] for s in summaries) / len(summaries) for k in keys}
    return {
        "timed_steps": summaries[0]["timed_steps"],
        **mean,
        "share": mean["all_reduce_ms_per_step"] / max(mean["step_ms"], 1e-9),
        "wait_share": mean["wait_ms_per_step"] / max(mean["step_ms"], 1e-9),
        "all_reduce_gb_per_second": mean["all_reduce_bytes_per_step"] / max(mean["all_reduce_ms_per_step"], 1e-9) / 1e6,
        "backend": backend,
        "per_process": summaries,
    }


class _Rewound(Exception):
    """A read found a halted iteration and the trainer went back to it (``--sync-free``)."""


class Trainer:
    """Runs one training from a :class:`TrainConfig` (``run()``), or resumes it.

    ``callbacks``: objects with ``on_start(trainer)`` (scene, model and strategy ready),
    ``on_step(trainer)`` (after each iteration) and ``on_end(trainer)`` (always, last); the browser
    viewer of ``cdcgs train --view`` is one (cdcgs.viewer.TrainingViewer).

    ``Trainer(config)`` makes the subclass of ``config.dist_mode`` where one declares it (its
    ``dist_mode``): "shards" makes a :class:`cdcgs.train.shard_training.ShardedTrainer` (each
    process of the launch holds a slice of the Gaussians), the same calls.
    """

    dist_mode = "data"  # every process holds every Gaussian (data parallelism)
    replicated = True  # False: each process holds a slice
    graph_steps = GraphSteps  # the replayed steps' class (a slice's render differs)
    _by_mode: typing.ClassVar[dict[str, type]] = {}  # dist_mode -> the subclass that trains it

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        Trainer._by_mode.setdefault(cls.dist_mode, cls)

    def __new__(cls, config: TrainConfig | None = None, *args, **kwargs):
        mode = getattr(config, "dist_mode", cls.dist_mode)
        if mode != cls.dist_mode:
            if cls is not Trainer:
                raise OptionError(f"{cls.__name__} trains --dist-mode {cls.dist_mode}, not {mode}")
            if mode not in Trainer._by_mode:
                raise OptionError(f"--dist-mode {mode}: no trainer of that mode (import cdcgs.train first)")
            cls = Trainer._by_mode[mode]
        return super().__new__(cls)

    def __init__(
        self, config: TrainConfig, strategy_options: dict | None = None, callbacks=(), ranks: Ranks | None = None
    ):
        self.config = config
        self.strategy_options = dict(strategy_options or {})
        self.callbacks = list(callbacks)
        # The processes of a torchrun launch (joined in run(); ``ranks``: the caller's own). Each
        # process of a machine takes a GPU of its own where there are enough.
        self._given_ranks = ranks
        self.ranks = ranks or Ranks.single()
        _, world, local_rank, local_world = _environment()
        name = rank_device(config.device, local_rank, local_world) if world > 1 and ranks is None else config.device
        self.device = resolve_device(name)
        self.out = config.out
        self.checkpoint_path = os.path.join(self.out, outputs.CHECKPOINT)
        self.signals = StopSignals()
        self.saved_step: int | None = None  # the iteration of the newest checkpoint in the folder
        self.peak_memory = {"train": 0, "eval": 0}  # bytes, of this process; evaluations apart
        self.peak_reserved = 0  # bytes torch's caching allocator held at most (freed blocks it keeps included)
        self.step_events: list[tuple[int, dict]] = []  # (iteration, log) of the last step's refinements
        # Reduced over the processes every step: (a signal is pending, a render met NaN, a halt) on any.
        self._flags = torch.zeros(3)
        self._nonfinite_at: int | None = None  # the iteration whose render met NaN, on this process
        # (wait ms, all-reduce ms, step ms, bytes reduced) of each timed step
        self._communication: list[tuple[float, float, float, int]] = []
        self._reduce_ms = self._wait_ms = 0.0
        self._reduce_bytes = 0
        self._visible: torch.Tensor | None = None  # selective Adam: the step's visible Gaussians
        # --dist-exchange colours: this process's views' colour gradients of the step, in batch order
        self._colour_grads: list[torch.Tensor] = []
        self.lookahead: Lookahead | None = None  # --sync-free
        self.graphs: GraphSteps | None = None  # --cuda-graph
        self.gamma_groups: GammaGroups | None = None  # the Γ passes' groups of views, with the graphs
        self.graph_off: str | None = None  # why the steps are not replayed as CUDA graphs
        self.balanced_steps = 0  # steps whose views the processes split by their counts (--dist-balance counts)
        self._snapshots: dict[int, dict] = {}  # --sync-free: iteration -> what the host needs to take it again

    # ----------------------------------------------------------------------------- set-up

    def _setup(self):
        config = self.config
        main = self.ranks.is_main
        if main and not config.resume and not config.overwrite:
            names = (outputs.CHECKPOINT, outputs.METRICS, outputs.PLY)
            previous = [name for name in names if os.path.isfile(os.path.join(self.out, name))]
            if previous:
                raise InputError(
                    self.out,
                    f"already holds a cdcgs run ({', '.join(previous)}); pass --resume to continue it, "
                    "--overwrite to replace it, or choose another --out",
                )
        removed = remove_temporary_files(self.checkpoint_path) if main else 0  # rank 0 holds the lock
        if removed:
            log.warning("%s: removed %d temporary file(s) of an interrupted checkpoint write", self.out, removed)
        resume_state = None
        if config.resume:
            resume_state = _upgrade_checkpoint(
                load_checkpoint(self.checkpoint_path, map_location="cpu"), self.checkpoint_path
            )
            saved = resume_state.get("config", {})
            if saved.get("data", {}).get("data") != config.data.data:
                trained_on = saved.get("data", {}).get("data")
                raise InputError(
                    self.checkpoint_path, f"the checkpoint was trained on {trained_on!r}, not {config.data.data!r}"
                )
            self.strategy_options = resume_state.get("strategy_options", self.strategy_options)
        self.strategy = make_strategy(config.strategy, self.strategy_options)
        self.strategy.check(config.iters)
        # The options left at none take the resumed run's values, else the preset's or the
        # strategy's; config.json records them.
        saved = resume_state.get("config") if resume_state else None
        self.config = config = resolve_defaults(config, self.strategy, saved)
        if getattr(self.strategy, "budget_schedule", "none") == "dash" and config.resolution_schedule != "dash":
            raise OptionError(
                "--budget-schedule dash grows the Gaussian budget with the training resolution: it needs "
                "--resolution-schedule dash"
            )
        if config.dist_balance == "counts" and config.dist_exchange == "colours":
            raise OptionError(
                "--dist-balance counts splits a step's views by their counts, and --dist-exchange colours rebuilds "
                "the SH gradients from each process's views in the default split: choose one"
            )
        self._check_sync_free()
        d = config.data
        self.scene = load_scene(d.data, device=self.device, progress=config.progress, **d.scene_options())
        # Each training view's camera, checked and built once (the render would redo it every step).
        self.cameras = [prepare_camera(v.viewmat, v.K, v.width, v.height) for v in self.scene.train]
        # Every random draw of the run comes from these two (torch generators are bound to a
        # device): the device one for strategies, splits and backgrounds, the CPU one for the
        # order of the views.
        self.generator = torch.Generator(device=self.device).manual_seed(config.seed)
        self.view_generator = torch.Generator().manual_seed(config.seed + 1)
        method = self.strategy.complexity_maps_method
        self.complexity_maps = ComplexityMaps(self.scene.train, method, self.device) if method else None
        self.resolution = self._resolution_schedule()
        self._scaled = {}  # (view index, downscale) -> (camera, uint8 target) of the resolution schedule
        self._shape, self._shape_key = None, None  # _bins' scales and opacities, and the parameters they are of
        if resume_state is None:
            self.model = GaussianModel.from_points(
                self.scene.points,
                self.scene.colors,
                max_sh_degree=config.sh_degree,
                init_opacity=config.init_opacity,
                scale_rule=config.scale_rule,
                scale_factor=config.init_scale,
                device=self.device,
            )
            self.optimizer = make_optimizer(
                self.model, config.lr, self.scene.extent, config.optimizer, batch_rule(config)
            )
            self.strategy_state = self.strategy.initialize_state(self.model)
            self.step = 0
            self.view_queue: list[int] = []
            self.history = {"step": [], "loss": [], "psnr": [], "gaussians": [], "eval": [], "strategy": []}
            self.train_seconds = 0.0
            self.guard = NumericGuard(self.device)
        else:
            held_out = resume_state.get("test_views")  # checkpoints before --test-views did not record it
            if held_out is not None and held_out != [v.name for v in self.scene.test]:
                raise InputError(
                    self.checkpoint_path,
                    f"the checkpoint held out {len(held_out)} test view(s) and this command's split holds out "
                    f"{len(self.scene.test)} others: resume with the run's own split (--test-every as it was, or "
                    f"--test-views {os.path.join(self.out, outputs.TEST_VIEWS)})",
                )
            self._restore_gaussians(resume_state)
            # The command's rates, eps and betas (its batch size's rule), not the checkpoint's.
            set_hyperparameters(self.optimizer, config.lr, self.scene.extent, batch_rule(config))
            self.strategy_state = {
                k: v.to(self.device) if torch.is_tensor(v) else v for k, v in resume_state["strategy_state"].items()
            }
            self.step = resume_state["step"]
            self.view_queue = resume_state["view_queue"]
            self.history = resume_state["history"]
            self.train_seconds = resume_state["train_seconds"]
            self.generator.set_state(resume_state["generator"])
            self.view_generator.set_state(resume_state["view_generator"])
            self.guard = NumericGuard(self.device, resume_state.get("guard"))
            self.saved_step = self.step
        fixed = background_color(config.background)
        self.background = torch.tensor(fixed or (0.0, 0.0, 0.0), device=self.device)
        self.lpips = lpips_metric(self.device)
        kinds = self.strategy.statistics()
        self.statistics = StatisticsSync(self.ranks, kinds) if self.ranks.distributed else None
        self._flags = torch.zeros(3, device=self.device)
        self.graphs = self._graph_steps()
        # A Γ pass's groups of views replayed from one CUDA graph, where the steps are
        self.gamma_groups = None
        if self.graphs is not None and self.complexity_maps is not None:
            self.gamma_groups = GammaGroups(self)
        sync_free = config.sync_free or self.graphs is not None
        self.lookahead = Lookahead(self.device, len(self.scene.train)) if sync_free else None
        config_json = {
            "train": config_to_dict(config),
            "processes": self.ranks.world,
            "strategy": self.strategy.config(),
            "scene": self._scene_summary(),
        }
        self._config_json = config_json  # written once every process has set up

    def _restore_gaussians(self, state: dict) -> None:
        """The model and its optimizer (with Adam's moments) from a checkpoint's ``state``."""
        self.model = GaussianModel.from_state_dict(state["model"], device=self.device)
        self.optimizer = make_optimizer(self.model, self.config.lr, self.scene.extent, self.config.optimizer)
        load_optimizer_state(self.optimizer, state["optimizer"])

    def _graph_steps(self) -> GraphSteps | None:
        """The steps replayed as CUDA graphs: with ``--cuda-graph``, refused with the reason where
        the training cannot take them; by default (none) wherever it can, else without, saying why
        on CUDA (``graph_off`` in metrics.json)."""
        choice = self.config.cuda_graph
        if choice is False:
            self.graph_off = "--no-cuda-graph"
            return None
        if choice is None:
            refusal = graph_refusal(self, default=True)
            if refusal is not None:
                self.graph_off = f"--cuda-graph {refusal[0]}: {refusal[1]}"
                if self.device.type == "cuda" and self.ranks.is_main:
                    print(f"steps run without CUDA graphs: {self.graph_off}")
                return None
        return self.graph_steps(self)

    def _agree_on_graphs(self) -> None:
        """On several processes: replay steps on all of them or on none. A replayed step holds the
        all-reduce, which NCCL needs every process to replay together, and a reason to refuse can
        hold on one process only (rank 0's viewer). Where one refuses, all train without graphs,
        and without --sync-free's slots unless it was asked for."""
        reasons = self.ranks.all_gather_object(self.graph_off if self.graphs is None else None)
        refused = [(rank, reason) for rank, reason in enumerate(reasons) if reason is not None]
        if self.graphs is None or not refused:
            return
        rank, reason = refused[0]
        self.graphs.release()
        self.graphs = self.gamma_groups = None
        self.graph_off = f"{reason} (on process {rank}, so on every process)"
        if not self.config.sync_free:
            self.lookahead = None
        if self.ranks.is_main and self.config.cuda_graph is None:
            print(f"steps run without CUDA graphs: {self.graph_off}")

    def _check_sync_free(self) -> None:
        config = self.config
        if not (config.sync_free or config.cuda_graph):
            return
        refusal = halt_refusal(config, self.strategy)
        if refusal is not None:
            name = "--cuda-graph" if config.cuda_graph else "--sync-free"
            raise OptionError(f"{name} {refusal[0]}: {refusal[1]}")

    @property
    def num_gaussians(self) -> int:
        """The Gaussians of the whole scene (this process's model holds them all, unless sharded)."""
        return self.model.num

    def _scene_summary(self) -> dict:
        s = self.scene
        return {
            "root": s.root,
            "source": s.source,
            "train_views": len(s.train),
            "test_views": len(s.test),
            "initial_points": int(s.points.shape[0]),
            "extent": s.extent,
            "notes": s.notes,
            "image_size": [s.train[0].width, s.train[0].height],
        }

    # ------------------------------------------------------------------------------ pieces

    def _next_view(self) -> int:
        """Views in a fresh random order each epoch (3DGS)."""
        if not self.view_queue:
            self.view_queue = torch.randperm(len(self.scene.train), generator=self.view_generator).tolist()
        return self.view_queue.pop()

    def _step_background(self) -> torch.Tensor:
        if self.config.background == "random":
            return torch.rand(3, device=self.device, generator=self.generator)
        return self.background

    def _resolution_schedule(self):
        """DashGaussian's resolution schedule over the training photos, or None."""
        config = self.config
        if config.resolution_schedule == "none":
            return None
        if self.complexity_maps is not None and getattr(self.strategy, "complexity_schedule", None) == "online":
            raise OptionError(
                "--resolution-schedule dash renders the training views at reduced sizes: it cannot be combined with "
                "--complexity-schedule online, which measures complexity on those renders (use the full schedule)"
            )
        from ..io.views import load_images

        missing = [view for view in self.scene.train if view.image is None]
        if missing:
            load_images(missing, device=self.device, progress=False)
        until = min(getattr(self.strategy, "densify_until", config.iters), config.iters)
        return dash_schedule([view.image for view in self.scene.train], until)

    def _downscale(self, step: int) -> int:
        """The resolution schedule's downscale at ``step``, re-read every 100 iterations (DashGaussian
        changes it at densification steps)."""
        return 1 if self.resolution is None else self.resolution.scale_at(step - step % 100)

    def _scaled_view(self, view_index: int, scale: int):
        """(camera, target) of a training view at 1/``scale`` of its size (floor), the photo
        resampled with antialiased bilinear filtering as DashGaussian does and kept as uint8 (as
        photos are); kept for reuse while the scale holds (the views of one scale at a time)."""
        key = (view_index, scale)
        if key not in self._scaled:
            if any(held != scale for _, held in self._scaled):
                self._scaled.clear()
            view = self.scene.train[view_index]
            height, width = view.height // scale, view.width // scale
            K = torch.as_tensor(view.K, dtype=torch.float64).clone()
            K[0] *= width / view.width
            K[1] *= height / view.height
            photo = view.image.permute(2, 0, 1)[None].float() / 255.0
            target = torch.nn.functional.interpolate(photo, size=(height, width), mode="bilinear", antialias=True)
            target = (target[0].permute(1, 2, 0).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).contiguous()
            self._scaled[key] = (prepare_camera(view.viewmat, K, width, height), target)
        return self._scaled[key]

    def _render(self, view_index: int, background=None, scale: int = 1, capacity: int | None = None):
        camera = self.cameras[view_index] if scale == 1 else self._scaled_view(view_index, scale)[0]
        return rasterize(
            **self.model.render_args(),
            camera=camera,
            background=self.background if background is None else background,
            antialiased=self.config.antialiased,
            capacity=capacity,
        )

    def _bins(self, view_index: int, counted: bool = False):
        """The projection and tile lists of a training view, without colours or image (Γ passes), as
        a :class:`cdcgs.render.PendingBins` (its ``finish()`` gives them), or, where the training
        knows the view's count (``--sync-free``, the CUDA graphs) and ``counted`` is False, as a
        :class:`cdcgs.render.RasterizeInfo` binned into the slots the lookahead gives it, which
        reads nothing back (:func:`cdcgs.complexity.complexity_over_views` reads the pass's flags
        once, and bins the views that overflowed again, counted).
        A pass bins every training view of the same Gaussians: their scales and opacities are
        computed once for it, again only when a parameter has changed (another tensor, or an
        in-place update: torch's version counter; weak references, so that no old parameter is
        kept alive or mistaken for a new one at its address)."""
        means, quats, scales_and_opacities = self._bin_inputs()
        shape = dict(camera=self.cameras[view_index], antialiased=self.config.antialiased)
        if self.lookahead is None:
            return start_bin_view(means, quats, **scales_and_opacities, **shape)
        capacity = None if counted else self.lookahead.capacity(view_index, self.model.num)
        if capacity is not None:
            self.lookahead.gamma_views["within"] += 1
            return bin_view(means, quats, **scales_and_opacities, **shape, capacity=capacity)
        self.lookahead.gamma_views["counted_again" if counted else "counted"] += 1
        return start_bin_view(means, quats, **scales_and_opacities, **shape)

    def _bin_inputs(self) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """(means, quats, {"scales", "opacities"}) of the Gaussians as the Γ passes bin them, the
        scales and opacities computed once for a pass (see :meth:`_bins`)."""
        params = [self.model.params[name] for name in self._SHAPE_PARAMS]
        if self._shape_key is None or any(
            ref() is not p or version != p._version for (ref, version), p in zip(self._shape_key, params)
        ):
            with torch.no_grad():
                self._shape = {"scales": self.model.scales(), "opacities": self.model.opacities()}
            self._shape_key = [(weakref.ref(p), p._version) for p in params]
        return self.model.params["means"].detach(), self.model.params["quats"].detach(), self._shape

    _SHAPE_PARAMS = ("log_scales", "opacity_logits")  # what the cached scales and opacities come from

    def _prime_counts(self) -> None:
        """With ``--sync-free`` (the replayed steps too): every training view's intersection count
        for the Gaussians the training starts (or resumes) from, from one binning of each view and
        one wait for all of them, so that no view's first render waits for its own count and the
        first steps can be replayed. A count only sizes a render's slots: a render that overflows
        them is taken again, as any (:mod:`cdcgs.train.lookahead`)."""
        lookahead = self.lookahead
        if lookahead is None or self.step >= self.config.iters:
            return
        scale = self._downscale(self.step + 1)
        model = self.model
        with torch.no_grad():
            shape = {"scales": model.scales(), "opacities": model.opacities()}
            means, quats = model.params["means"].detach(), model.params["quats"].detach()
            counts = []
            for view in range(len(self.scene.train)):
                camera = self.cameras[view] if scale == 1 else self._scaled_view(view, scale)[0]
                pending = start_bin_view(means, quats, **shape, camera=camera, antialiased=self.config.antialiased)
                counts.append(pending.count_on_device)
            values = torch.cat(counts).tolist() if counts else []
        lookahead.prime(values, model.num, scale, self.step)

    def state_dict(self) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "strategy_state": self.strategy_state,
            "strategy_options": self.strategy_options,
            "step": self.step,
            "view_queue": list(self.view_queue),
            "test_views": [v.name for v in self.scene.test],
            "history": self.history,
            "train_seconds": self.train_seconds,
            "generator": self.generator.get_state(),
            "view_generator": self.view_generator.get_state(),
            "guard": self.guard.state_dict(),
            "config": config_to_dict(self.config),
            "processes": self.ranks.world,
            "batch_size": self.config.batch_size,
        }

    def save(self, ply: bool = True) -> None:
        """Write the checkpoint (and the PLY), after the numeric guard's check: a state with
        non-finite numbers is never written. The first signal does not cut a save."""
        if self.lookahead is not None:
            self._settle()  # a halted iteration: the state before it is the one to write
        self.check_numbers(params=True)
        with self.signals.deferred():
            if self.ranks.is_main:  # the others hold the same state
                save_checkpoint(self.checkpoint_path, self.state_dict())
                if ply:
                    write_ply(os.path.join(self.out, outputs.PLY), self.model.to_ply())
            self.saved_step = self.step

    def check_numbers(self, params: bool = False) -> None:
        """The numeric guard's check (a host synchronisation); raises TrainingDiverged. On several
        processes every one checks its own numbers and they agree: any failure stops them all."""
        if not self.ranks.distributed:
            self.guard.check(self.step, self.optimizer, self.model.params if params else None, self._last_good())
            return
        error = None
        try:
            self.guard.check(self.step, self.optimizer, self.model.params if params else None, self._last_good())
        except TrainingDiverged as err:
            error = err
        if error is None and self._nonfinite_at is not None:
            error = self._nonfinite_error()
        reports = self.ranks.all_gather_object(None if error is None else str(error))
        if error is not None:
            raise error
        failed = [(rank, report) for rank, report in enumerate(reports) if report]
        if failed:
            rank, report = failed[0]
            raise TrainingDiverged(f"rank {rank}: {report}")

    def _nonfinite_error(self) -> TrainingDiverged:
        """The error of a render that met NaN: the update before ``_nonfinite_at`` made it so."""
        step = self._nonfinite_at - 1
        bad = [name for name, p in self.model.params.items() if not torch.isfinite(p).all()] or ["the parameters"]
        cause = f"the update of iteration {step} made {', '.join(bad)} NaN or infinite"
        return self.guard.diverged(step, self.optimizer, cause, self._last_good())

    def _last_good(self) -> str:
        if self.saved_step is None:
            return (
                "No checkpoint had been written yet, so there is no good state to resume "
                "(--checkpoint-every sets how often one is written)."
            )
        return (
            f"The last good state, iteration {self.saved_step}, is in {self.checkpoint_path}: "
            "--resume continues from it (the learning rate options may change)."
        )

    def _agree_on_lpips(self) -> None:
        """Score LPIPS with the networks that every process has: each looks for the weights on
        its own machine, and an evaluation split over the processes would otherwise score some
        views and not others. A network missing anywhere is left out everywhere, and the note
        says on which process and why."""
        have = self.ranks.all_gather_object((sorted(self.lpips.nets), self.lpips.note))
        names = [set(names) for names, _ in have]
        missing = set.union(*names) - set.intersection(*names)
        if not missing:
            return
        for name in missing & set(self.lpips.nets):
            del self.lpips.nets[name]
        nets = ", ".join(f"LPIPS-{name}" for name in sorted(missing))
        why = "; ".join(f"process {rank}: {note}" for rank, (_, note) in enumerate(have) if missing - names[rank])
        self.lpips.note = f"{nets} not scored: some processes lack the weights ({why})"

    def _peak_memory(self, part: str) -> None:
        """Add the peak GPU memory since the last call to ``part`` ("train" or "eval")."""
        if self.device.type == "cuda":
            peak = torch.cuda.max_memory_allocated(self.device)
            self.peak_memory[part] = max(self.peak_memory[part], peak)
            self.peak_reserved = max(self.peak_reserved, torch.cuda.max_memory_reserved(self.device))
            torch.cuda.reset_peak_memory_stats(self.device)

    def _communication_summary(self) -> dict:
        """This process's communication over the timed steps (one in ``TIME_COMMUNICATION_EVERY``,
        each synchronised around its parts): ``wait_ms_per_step``, how long it waited for the
        slowest process before the all-reduce (a one-number all-reduce: the batch's imbalance), and
        ``all_reduce_ms_per_step``, the gradients' all-reduce after that wait, with its bytes."""
        if not self._communication:
            return {"timed_steps": 0}
        wait_ms, reduce_ms, step_ms, size = (sum(c) / len(self._communication) for c in zip(*self._communication))
        return {
            "timed_steps": len(self._communication),
            "wait_ms_per_step": wait_ms,
            "all_reduce_ms_per_step": reduce_ms,
            "all_reduce_bytes_per_step": size,
            "step_ms": step_ms,
        }

    def _evaluate(self, final: bool, render_round=None) -> dict:
        """The held-out metrics (every process its share of the test views); ``render_round``:
        :func:`cdcgs.train.evaluate.evaluate`'s collective render, for a sharded scene."""
        self.check_numbers(params=True)
        self._peak_memory("train")  # the LPIPS networks' activations are not the training's memory
        save_dir = os.path.join(self.out, "test_renders") if (final and self.config.save_renders) else None
        metrics = evaluate(
            self.model,
            self.scene.test,
            background=self.background,
            antialiased=self.config.antialiased,
            save_dir=save_dir,
            lpips=self.lpips,
            ranks=self.ranks if self.ranks.distributed else None,
            render_round=render_round,
        )
        metrics["num_gaussians"] = self.num_gaussians
        self._peak_memory("eval")
        summary = {k: metrics.get(k) for k in ("psnr", "ssim", "lpips_vgg", "lpips_alex", "num_gaussians")}
        self.history["eval"].append({"step": self.step, **summary, **allocator_now(self.device)})
        return metrics

    # -------------------------------------------------------------------------------- loop

    def train_step(self) -> dict:
        """One step: ``--batch-size`` views (this process's share of them), each rendered, scored
        and back-propagated with the strategy's per-view hooks; the gradients and statistics
        summed over the views and the processes (Adam steps their mean); the strategy's refinements of the
        step's iterations; one optimizer step. Reads nothing back from the device itself (the
        render reads its intersection count) except where the strategy is about to change the
        Gaussians. Returns the strategy's logs of the step merged (each also in ``step_events``
        with its own iteration)."""
        config = self.config
        first = self.step + 1
        count = min(config.batch_size, config.iters - self.step)
        last = self.step + count
        if self.lookahead is not None:
            self._snapshots[first] = self._host_state()
        timed = self.ranks.distributed and (first // config.batch_size) % TIME_COMMUNICATION_EVERY == 10
        if timed:
            self._synchronize()
            step_start = time.perf_counter()
        views, backgrounds = self._start_step(first, last)
        if self._replayed(first, last, views, backgrounds, timed):
            return {}
        if self.statistics is not None:
            self.statistics.begin(self.strategy_state, halts=self.lookahead is not None)
        visible = None
        seen = []  # (loss, PSNR, context) of each view, recorded once every view of the step is rendered
        for position in self.positions(first, views):
            view = self._view_backward(first + position, views[position], backgrounds[position])
            if view is None:  # on several processes: a render met NaN; the others learn it below
                break
            seen.append(view)
            if config.optimizer == "selective":
                info = view[2].info
                visible = info.visible if visible is None else visible | info.visible
        # After the step's last render: with --sync-free, a halt that a later view of the batch sets
        # also stops the earlier views' records (the step is taken again from its first view). On
        # several processes the halt of any process reaches every one with the all-reduce, which
        # holds back the statistics' additions (StatisticsSync.finish) and comes before the guard's
        # records.
        halt = None if self.lookahead is None else self.lookahead.halt
        for _, _, ctx in seen:
            self.strategy.observe(ctx, self.strategy_state)
        if config.optimizer == "selective" and visible is None:
            visible = torch.zeros(self.model.num, dtype=torch.bool, device=self.device)
        cameras = [self.cameras[view] for view in views] if self._exchanges_colours else None
        self._reduce(count, visible, timed, cameras=cameras)
        for loss, image_psnr, _ in seen:
            self.guard.record(loss, image_psnr, halt)
        self.step = last
        self.step_events = []
        for iteration in range(first, last + 1):
            if self.strategy.refines_at(iteration):
                self._settle_in_step()  # a refinement reads the Gaussians: no halted iteration before it
                # On several processes the parameters too: a refinement may render views (CDC's Γ
                # pass) that meet NaN on one process only, which must not stop it alone.
                self.check_numbers(params=self.ranks.distributed)
                self._synchronize()  # the step's kernels are not the refinement's time
                refine_start = time.perf_counter()
                log = self.strategy.refine(self._context(iteration), self.strategy_state)
                if log:
                    self._synchronize()
                    log["refine_seconds"] = time.perf_counter() - refine_start
                    self.step_events.append((iteration, log))
                if self.statistics is not None:
                    # the new Gaussians' statistics
                    self.statistics.begin(self.strategy_state, halts=self.lookahead is not None)
        adam = {} if self.lookahead is None else {"halt": self.lookahead.halt}
        if self.folds_batch_mean and count != 1:  # the gradients are the views' sums (_reduce)
            adam["gradient_scale"] = 1.0 / count
        if config.optimizer == "selective":
            self.optimizer.step(self._visible if self._visible.shape[0] == self.model.num else None, **adam)
        else:
            self.optimizer.step(**adam)
        self.optimizer.zero_grad(set_to_none=True)
        self.strategy.after_step(self._context(last), self.strategy_state)
        if timed:
            self._synchronize()
            step_ms = (time.perf_counter() - step_start) * 1e3
            self._communication.append((self._wait_ms, self._reduce_ms, step_ms, self._reduce_bytes))
        merged = {}
        for _, log in self.step_events:
            merged.update(log)
        return merged

    def _replayed(self, first: int, last: int, views: list[int], backgrounds: list, timed: bool) -> bool:
        """Take the step of iterations ``first`` to ``last`` as a replayed graph where it can be
        (a whole batch: the last, shorter one runs as before; a timed step runs as before, its
        parts timed apart) and return True, else False."""
        if self.graphs is None or last - first + 1 != self.config.batch_size or timed:
            return False
        if not self.graphs.take(first, views, backgrounds):
            return False
        self.step = last
        self.step_events = []
        self.strategy.after_step(self._context(last), self.strategy_state)
        return True

    def _start_step(self, first: int, last: int) -> tuple[list[int], list[torch.Tensor]]:
        """The rates, the SH degree and the draws of the step of iterations ``first`` to ``last``:
        (its views, their backgrounds). Every process draws the whole batch from the same streams
        and renders its positions of it; the step's draws come from a generator seeded by (seed,
        step)."""
        config = self.config
        self._set_position_lr(first)
        for iteration in range(first, last + 1):
            if iteration % config.sh_every == 0 and self.model.sh_degree < self.model.max_sh_degree:
                self.model.sh_degree += 1
        views = [self._next_view() for _ in range(last - first + 1)]
        self.generator.manual_seed(step_seed(config.seed, first))
        return views, [self._step_background() for _ in views]

    def _context(self, iteration: int, info=None, view_index: int | None = None) -> StepContext:
        return StepContext(
            step=iteration,
            total_steps=self.config.iters,
            model=self.model,
            optimizer=self.optimizer,
            info=info,
            view_index=view_index,
            extent=self.scene.extent,
            generator=self.generator,
            render=self._render,
            bins=self._bins,
            gamma_groups=self.gamma_groups,
            views=self.scene.train,
            complexity_maps=self.complexity_maps,
            ranks=self.ranks if self.ranks.distributed else None,
            resolution_scale=None if self.resolution is None else self._downscale(iteration),
            halt=None if self.lookahead is None else self.lookahead.halt,
        )

    def _set_position_lr(self, first: int) -> None:
        """The means' learning rate of the step that starts at iteration ``first``."""
        config = self.config
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                decay_from = 0 if self.resolution is None else self.resolution.decay_from()
                rate = position_lr(first, config.iters, config.lr, self.scene.extent, decay_from)
                group["lr"] = rate * batch_rule(config)[0]

    # ------------------------------------------------------------------ --sync-free

    def _host_state(self) -> dict:
        """What the host needs to take the next iteration again: the step, the view order and its
        generator, the SH degree and Adam's step counts (the device's state stays as it was while
        halted; the step's own draws are seeded by its number)."""
        return {
            "step": self.step,
            "view_queue": list(self.view_queue),
            "view_generator": self.view_generator.get_state(),
            "sh_degree": self.model.sh_degree,
            "adam_steps": [(state, float(state["step"])) for state in self.optimizer.state.values() if "step" in state],
        }

    def _settle(self) -> bool:
        """Read the device's flags (one host synchronisation). When an iteration halted, go back to
        it (its overflowed view is rendered with the count the device recorded) and return True;
        when it met NaN, stop as a render that reads its count does. On several processes every
        process reads at the same iterations, and they agree (:meth:`_agree_on_halt`)."""
        distributed = self.ranks.distributed
        if distributed:
            # A collective the process group's watchdog tracks, queued before the host waits: the
            # replayed steps' collectives are not tracked, and a process that died would otherwise
            # leave the others waiting here past --dist-timeout.
            self.ranks.all_reduce_(torch.zeros(1, device=self.device))
        halted = self.lookahead.read(always=distributed)
        snapshots, self._snapshots = self._snapshots, {}
        if distributed:
            halted = self._agree_on_halt(halted)
        if halted is None:
            return False
        start = max(step for step in snapshots if step <= halted.step)
        state = snapshots[start]
        self.lookahead.rewinds += 1
        self.lookahead.redone += self.step - state["step"]
        self.optimizer.zero_grad(set_to_none=True)
        self.step, self.view_queue = state["step"], state["view_queue"]
        self.view_generator.set_state(state["view_generator"])
        self.model.sh_degree = state["sh_degree"]
        for adam, value in state["adam_steps"]:
            adam["step"].fill_(value)
        self._set_position_lr(self.step + 1)  # the rates in force at the halted iteration
        if not halted.overflowed:
            self._nonfinite_at = halted.step
            raise self._nonfinite_error()
        return True

    def _agree_on_halt(self, halted: Halted | None) -> Halted | None:
        """On several processes, at a read: every process's counts (so that all know the same ones,
        and a replayed step is taken by all or by none) and their halts, in one exchange. The
        earliest halted iteration of any process is the one all go back to; NaN there stops all.
        A process whose halt came only from another's (through the all-reduce) reports none."""
        own = None if halted is None or halted.cause == 0 else (halted.step, halted.cause, halted.count)
        reports = self.ranks.all_gather_object((self.lookahead.known(), own, halted is not None))
        self.lookahead.merge([known for known, _, _ in reports])
        halts = [report for _, report, _ in reports if report is not None]
        if not halts:
            if any(flagged for _, _, flagged in reports):
                raise RuntimeError("a process's halt flag was set, yet no process recorded the render that set it")
            return None
        step = min(h[0] for h in halts)
        cause = max(h[1] for h in halts if h[0] == step)  # NaN (2 + input) before an overflow (1)
        return Halted(step, cause, max(h[2] for h in halts if h[0] == step))

    def _settle_in_step(self) -> None:
        """:meth:`_settle` inside a step: going back ends the step (:class:`_Rewound`)."""
        if self.lookahead is not None and self._settle():
            raise _Rewound

    def _view_backward(self, iteration: int, view_index: int, background: torch.Tensor):
        """Render one training view at ``iteration`` and add its loss's gradients; returns its
        (loss, PSNR, step context with the render's info) for the guard and the strategy's
        statistics, which the step records after its last render. A render that meets NaN
        parameters stops a single process at once; on several, it returns None and the processes
        stop together at the next check (:meth:`check_numbers`)."""
        view = self.scene.train[view_index]
        scale = self._downscale(iteration)
        lookahead = self.lookahead
        capacity = None if lookahead is None else lookahead.capacity(view_index, self.model.num, scale)
        try:
            image, _, info = self._render(view_index, background, scale, capacity)
        except NonFiniteError:
            # The render checks the parameters it reads: the last update made them non-finite,
            # unless an earlier iteration halted (--sync-free), which is then taken again. On
            # several processes a read is a collective, which this process alone cannot take: the
            # processes stop together at the next check.
            if self.ranks.distributed:
                self._nonfinite_at = self._nonfinite_at or iteration
                return None
            self._settle_in_step()
            self._nonfinite_at = iteration
            raise self._nonfinite_error() from None
        if lookahead is not None and capacity is None:
            lookahead.counted(view_index, info.num_intersections, self.model.num, scale, iteration)
        elif lookahead is not None:
            lookahead.note(info, iteration, view_index, self.model.num, scale)
        photo = view.image if scale == 1 else self._scaled_view(view_index, scale)[1]
        return self._learn(image, photo, info, iteration, view_index)

    def _learn(self, image, photo, info, iteration: int, view_index: int | None = None) -> tuple:
        """A render's loss against its ``photo`` back-propagated with the strategy's per-view hooks
        (a replayed step passes no ``view_index``): (loss, PSNR, step context), as the step records
        them after its last render."""
        loss, image_psnr = self._loss(image, photo)
        ctx = self._context(iteration, info, view_index)
        self.strategy.before_backward(ctx, self.strategy_state)
        regularizer = self.strategy.regularizer(ctx)
        if regularizer is not None:
            loss = loss + regularizer
        self._backward(loss, info)  # each view's full gradient; the step averages them
        return loss, image_psnr, ctx

    @property
    def folds_batch_mean(self) -> bool:
        """Whether a step of several views hands Adam its views' summed gradients and the division
        by their count as ``gradient_scale`` (folded into the moments' rates: no pass over the
        gradients), as :class:`cdcgs.train.optim.FusedAdam` takes it; another optimizer
        (``--optimizer torch-adam``) gets the mean."""
        return isinstance(self.optimizer, FusedAdam)

    @property
    def _exchanges_colours(self) -> bool:
        return self.ranks.distributed and self.config.dist_exchange == "colours"

    def _backward(self, loss: torch.Tensor, info) -> None:
        """Back-propagate one view's loss; with ``--dist-exchange colours``, keep its colours'
        gradient as the SH adjoint reads it (zero where the colour was clamped at 0 or the
        Gaussian culled), for the other processes (:meth:`_rebuild_sh_gradients`)."""
        if not self._exchanges_colours:
            loss.backward()
            self._mark_step_graph()
            return
        info.colors.retain_grad()
        loss.backward()
        self._mark_step_graph()
        grad = info.colors.grad
        if grad is None:
            grad = torch.zeros_like(info.colors)
        passes = (info.colors > 0) & (info.radii[:, :1] > 0)
        self._colour_grads.append(torch.where(passes, grad, torch.zeros((), device=grad.device)))

    def _mark_step_graph(self) -> None:
        """Where steps are captured, tag the graph this backward pass went through, so that the next
        capture frees it first if a reference cycle still holds it (:func:`free_earlier_graphs`)."""
        if self.graphs is not None:
            mark_step_graph(self.model.params.values())

    def _rebuild_sh_gradients(self, count: int, cameras) -> int:
        """``--dist-exchange colours``: gather every process's colour gradients of the step's
        ``count`` views (``cameras``, in batch order) and set the spherical harmonics' gradients to
        the sum of the views' SH adjoints in batch order on every process (so that all get the same
        bits), divided by ``count`` unless Adam takes the division (``folds_batch_mean``). Returns
        the bytes gathered."""
        world, num = self.ranks.world, self.model.num
        slots = -(-count // world)  # views per process, the last ones padded with zeros
        grads, self._colour_grads = self._colour_grads, []
        grads += [torch.zeros(num, 3, device=self.device)] * (slots - len(grads))
        mine = torch.stack(grads)
        gathered = self.ranks.all_gather_(mine)  # [world, slots, N, 3]
        params = self.model.params
        means, sh_dc, sh_rest = (params[name].detach() for name in ("means", "sh_dc", "sh_rest"))
        passing_radii = torch.ones(num, 2, dtype=torch.int32, device=self.device)
        passing_colors = torch.ones(num, 3, device=self.device)  # the gradients are masked already
        total_dc = total_rest = None
        for position in range(count):
            grad = gathered[position % world, position // world]
            _, dc, rest = sh_adjoint(
                means, sh_dc, sh_rest, self.model.sh_degree, cameras[position], passing_radii, passing_colors, grad
            )
            total_dc = dc if total_dc is None else total_dc + dc
            total_rest = rest if total_rest is None else total_rest + rest
        if not self.folds_batch_mean:
            total_dc.div_(count)
            total_rest.div_(count)
        params["sh_dc"].grad, params["sh_rest"].grad = total_dc, total_rest
        return 4 * gathered.numel()

    def _loss(self, image: torch.Tensor, photo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(the photometric loss of a render against its uint8 photo, the render's PSNR)."""
        config = self.config
        if config.fused_loss:  # the photo stays uint8 on the device; the kernels read it as such
            loss, mse = fused_photometric_loss(image, photo, config.ssim_weight)
            return loss, mse_to_psnr(mse)
        target = photo.float() / 255.0
        return photometric_loss(image, target, config.ssim_weight), psnr(image.detach(), target)

    def _balance_refusal(self) -> str | None:
        """Why ``--dist-balance counts`` cannot split any step of this run, or None."""
        world, batch = self.ranks.world, self.config.batch_size
        if world < 2:
            return "one process"
        if not splits_by_counts(batch, world):
            return f"--batch-size {batch} is not two views or more for each of {world} processes"
        if self.lookahead is None:
            return f"no counts to split by (--sync-free or the replayed steps give them; {self.graph_off})"
        return None

    def positions(self, first: int, views: list[int]) -> list[int]:
        """The positions of the step's batch (``views``, beginning at iteration ``first``) that
        this process renders: rank, rank + processes, ..., or with ``--dist-balance counts`` the
        split of :func:`cdcgs.train.distributed.balanced_positions` by the views' counts that every
        process knows alike (the agreed ones, so all split alike), where each view has one at this
        resolution and each process gets two views or more; a view's cost is the slots it would
        take now (its count grown with the Gaussians since)."""
        count, rank, world = len(views), self.ranks.rank, self.ranks.world
        lookahead = self.lookahead
        splits = world > 1 and splits_by_counts(count, world)
        if self.config.dist_balance == "counts" and lookahead is not None and splits:
            scale = self._downscale(first)
            costs = [lookahead.capacity(v, self.model.num, scale, agreed=True) for v in views]
            if all(cost is not None for cost in costs):
                self.balanced_steps += 1
                return balanced_positions(costs, rank, world, turn=first // count)
        return my_positions(count, rank, world)

    def _reduce(
        self,
        count: int,
        visible: torch.Tensor | None,
        timed: bool,
        flags: torch.Tensor | None = None,
        cameras: list | None = None,
    ) -> None:
        """Sum the step's gradients over its ``count`` views (on several processes: one flat
        all-reduce that also carries the statistics' additions, the visible masks and the flags:
        a pending signal, a render that met NaN and, with --sync-free, the halt). ``flags``: those
        three on the device already (a replayed step's); by default set from the host's state.
        With ``--dist-exchange colours`` the spherical harmonics' gradients stay out of the
        all-reduce and are rebuilt from the views' colour gradients (``cameras``: the step's views'
        cameras, in batch order). The sums are divided by ``count`` unless Adam takes the division
        (``folds_batch_mean``)."""
        params = [group["params"][0] for group in self.optimizer.param_groups]
        colours = self._exchanges_colours
        if colours:
            sh = {id(self.model.params[name]) for name in ("sh_dc", "sh_rest")}
            params = [p for p in params if id(p) not in sh]
        self._visible = visible
        divide = not self.folds_batch_mean
        if not self.ranks.distributed:
            self.ranks.reduce_gradients(params, count, divide=divide)
            return
        if flags is None:
            # Set on the device: torch.tensor(..., device=cuda) copies from pageable memory, which
            # waits for the stream, and the host would lose its lead on the GPU at every step.
            flags = torch.zeros(3, device=self.device)
            for index, raised in enumerate((self.signals.pending is not None, self._nonfinite_at is not None)):
                if raised:
                    flags[index] = 1.0
            if self.lookahead is not None:
                flags[2:].copy_(self.lookahead.halt)
        extras = [*self.statistics.deltas(self.strategy_state), flags]
        if visible is not None:
            extras.append(visible.float())
        if timed:
            # First wait for the slowest rank (a one-number all-reduce), so that the gradients'
            # all-reduce is timed alone: the wait is the batch's imbalance, not communication.
            self._synchronize()
            start = time.perf_counter()
            self.ranks.all_reduce_(torch.zeros(1, device=self.device))
            self._synchronize()
            self._wait_ms = (time.perf_counter() - start) * 1e3
            self._reduce_bytes = 4 * (sum(p.numel() for p in params) + sum(e.numel() for e in extras))
            start = time.perf_counter()
        reduced = self.ranks.reduce_gradients(params, count, extras, divide=divide)
        if visible is not None:
            self._visible = reduced.pop() > 0
        self._flags.copy_(reduced.pop())  # one buffer: a replayed step writes the same one
        halt = None
        if self.lookahead is not None:  # any process's halt stops every process's updates
            halt = self.lookahead.halt
            torch.maximum(halt, (self._flags[2:] > 0).to(halt.dtype), out=halt)
        self.statistics.finish(self.strategy_state, reduced, halt)
        if colours:
            gathered = self._rebuild_sh_gradients(count, cameras)
            if timed:
                self._reduce_bytes += gathered
        if timed:
            self._synchronize()
            self._reduce_ms = (time.perf_counter() - start) * 1e3

    def _synchronize(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _raise_pending(self, agreed: bool = True) -> None:
        """Stop cleanly where a signal is pending. One process: at once. Several: only at an
        ``agreed`` point (every process passes it at the same iteration), where the reduced flag
        says whether any process has one, so that all stop together."""
        if not self.ranks.distributed:
            self.signals.raise_pending()
            return
        if agreed and float(self._flags[0]) > 0:
            raise Interrupted(self.signals.pending or signal.SIGTERM, clean=True)

    def run(self) -> dict:
        """Train to ``config.iters`` (from the checkpoint with ``resume``), evaluate, write outputs.

        The run folder is locked meanwhile (:class:`cdcgs.train.outputs.RunLock`); a folder this
        call created is removed again when the run fails before writing anything into it.
        SIGINT and SIGTERM end the run with :class:`Interrupted` (see :mod:`cdcgs.train.interrupt`):
        the first, during the training loop, after a whole iteration and with a checkpoint of it;
        elsewhere, or a second one, at once and writing nothing more.

        In a torchrun launch (docs/distributed.md) every process calls this: they join one
        process group, rank 0 holds the lock and writes, and a failure of one stops the others
        (:class:`cdcgs.train.distributed.RankFailed`).
        """
        config = self.config
        if self._given_ranks is None:
            # Before joining the group: a process that refuses the options after joining may
            # close it while another is still connecting, which then fails with Gloo's error.
            _check_batch(config.batch_size, _environment()[1])
            self.ranks = Ranks.from_environment(
                self.device, config.dist_backend, config.dist_timeout, spread=config.device in ("auto", "cuda")
            )
        finished = False
        try:
            _check_batch(config.batch_size, self.ranks.world)
            if self.ranks.is_main:
                result = self._run_main()
            else:
                with self.signals:
                    result = self._run()
            finished = True
            return result
        except Exception as err:
            # Said before the group closes, which may wait for a peer stuck in an exchange (then
            # nothing else would tell). Bad input is reported by the command line, as one line.
            if self.ranks.distributed and not isinstance(err, (InputError, OptionError)):
                known = isinstance(err, (RankFailed, RankDrift, TrainingDiverged))
                said = f"{type(err).__name__}: {err}" if known else "".join(traceback.format_exception(err)).rstrip()
                log.error("rank %d failed: %s", self.ranks.rank, said)
            raise
        finally:
            if self.graphs is not None:
                # A graph that captured NCCL's all-reduce must go before its process group: a
                # 2-GPU run whose last steps were replayed hung at the group's destruction. (After
                # a failure no wait: a process that died would leave the others' wait unanswered.)
                self.graphs.release()
                if finished:
                    self._synchronize()
            if self._given_ranks is None:
                self.ranks.close(wait=finished)

    def _run_main(self) -> dict:
        """Rank 0's run (the only one of a single process): the folder and its lock, then
        :meth:`_run`. A failure before the set-up is reported to the other processes."""
        created = False
        try:
            if os.path.exists(self.out) and not os.path.isdir(self.out):
                raise InputError(self.out, "--out names a file, not a folder")
            created = not os.path.exists(self.out)
            os.makedirs(self.out, exist_ok=True)
        except Exception as err:  # the others wait for the set-up's verdict
            self.ranks.all_ok(err, "set-up")
        try:
            with contextlib.ExitStack() as stack:
                stack.enter_context(self.signals)
                try:
                    lock = stack.enter_context(outputs.RunLock(self.out))
                except Exception as err:  # (another training holds the folder)
                    self.ranks.all_ok(err, "set-up")
                if lock.stale:
                    log.warning(
                        "%s: took over the lock of a training that is gone (pid %s on %s, started %s)",
                        self.out,
                        lock.stale.get("pid"),
                        lock.stale.get("host"),
                        lock.stale.get("started"),
                    )
                return self._run()
        except BaseException as err:
            if isinstance(err, Interrupted):
                self._report_stop(err)
            if created and os.path.isdir(self.out) and not os.listdir(self.out):
                os.rmdir(self.out)
            raise

    def _report_stop(self, stop: Interrupted) -> None:
        if stop.clean:
            print(
                f"stopped by {stop} at iteration {self.saved_step}: checkpoint and PLY written to {self.out} "
                "(continue with --resume)"
            )
        elif self.saved_step is not None:
            print(
                f"stopped at once by {stop}: nothing more written; the checkpoint in {self.out} holds iteration "
                f"{self.saved_step} (continue with --resume)"
            )
        else:
            print(f"stopped at once by {stop}: no checkpoint was written")

    def _run(self) -> dict:
        error = None
        try:
            self._setup()
        except Exception as err:  # every process learns of it and stops
            error = err
        self.ranks.all_ok(error, "set-up")
        if self.ranks.distributed:  # after the verdict: a collective inside the set-up could meet a failed one
            self._agree_on_lpips()
            self._agree_on_graphs()
        if self.ranks.is_main and self.config.dist_balance == "counts":
            why = self._balance_refusal()
            if why is not None:
                print(f"--dist-balance counts: {why}; the views split by position")
        try:  # agreed on too: a failed write stops every process with its cause, not by a timeout
            if self.ranks.is_main:
                outputs.write_json(os.path.join(self.out, outputs.CONFIG), self._config_json)
                outputs.write_view_names(os.path.join(self.out, outputs.TEST_VIEWS), self.scene.test)
        except Exception as err:
            error = err
        self.ranks.all_ok(error, f"writing {outputs.CONFIG} and {outputs.TEST_VIEWS}")
        config = self.config
        from tqdm import tqdm

        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
        started = []
        bar = tqdm(
            total=config.iters,
            initial=self.step,
            disable=not (config.progress and self.ranks.is_main),
            unit="it",
            dynamic_ncols=True,
        )
        try:
            for callback in self.callbacks:
                callback.on_start(self)
                started.append(callback)
            with self.signals.deferred():
                start = time.perf_counter()
                self._prime_counts()
                self.train_seconds += time.perf_counter() - start
                while self.step < config.iters:
                    self._iteration(bar)
                    self._raise_pending(agreed=False)
        except Interrupted as stop:
            bar.close()
            if stop.clean:
                self.save()
            raise
        finally:
            for callback in reversed(started):
                callback.on_end(self)
        bar.close()
        return self.finish()

    def _iteration(self, bar) -> None:
        """One training step and what follows it: callbacks, logs, evaluation, checkpoint (each
        when the step reaches its iteration)."""
        config = self.config
        before = self.step
        start = time.perf_counter()
        try:
            self.train_step()
        except _Rewound:
            self.train_seconds += time.perf_counter() - start
            self._show_rewind(bar)
            return
        if self.lookahead is not None and self._reads_at(before, self.step) and self._settle():
            self.train_seconds += time.perf_counter() - start
            self._show_rewind(bar)
            return
        self.train_seconds += time.perf_counter() - start  # with --sync-free, the read's wait for the GPU
        for callback in self.callbacks:
            callback.on_step(self)
        for iteration, strategy_log in self.step_events:
            self.history["strategy"].append({"step": iteration, **strategy_log})
        step, last = self.step, self.step == config.iters
        logged = crossed(before, step, config.log_every) or last
        report = not config.progress and (crossed(before, step, 1000) or last)
        if logged or report:
            self.check_numbers()  # where the running means are read anyway: one host synchronisation
            self._raise_pending()
            loss, psnr_value = self.guard.means()
            if logged:
                for key, value in (
                    ("step", step),
                    ("loss", loss),
                    ("psnr", psnr_value),
                    ("gaussians", self.num_gaussians),
                ):
                    self.history[key].append(value)
                # the training time so far (a run resumed from an older checkpoint starts this list there)
                self.history.setdefault("train_seconds", []).append({"step": step, "seconds": self.train_seconds})
                memory = allocator_now(self.device)
                if memory:  # a run resumed from an older checkpoint starts the timeline there
                    self.history.setdefault("gpu_memory", []).append({"step": step, **memory})
            bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{psnr_value:.2f}", gaussians=self.num_gaussians, refresh=False)
            if report and self.ranks.is_main:
                print(
                    f"[{step}/{config.iters}] loss {loss:.4f}, PSNR {psnr_value:.2f} dB, "
                    f"{self.num_gaussians} Gaussians, {step / max(self.train_seconds, 1e-9):.1f} it/s",
                    flush=True,
                )
        bar.update(step - before)
        if self.ranks.distributed and crossed(before, step, config.check_ranks_every):
            self._check_ranks(step)
        if crossed(before, step, config.eval_every) and not last and self.scene.test:
            self._raise_pending()  # a signal during the step: stop before a long evaluation
            metrics = self._evaluate(final=False)
            if self.ranks.is_main:
                bar.write(
                    f"[{step}] test PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, {self.num_gaussians} Gaussians"
                )
        if crossed(before, step, config.checkpoint_every) and not last:
            self._raise_pending()  # the interrupt's checkpoint is this one, with the PLY
            self.save(ply=False)

    def _result_extras(self) -> dict:
        """Entries of metrics.json that only some trainings have."""
        return {}

    def _check_ranks(self, step: int) -> None:
        """Every ``--check-ranks-every`` iterations on several processes: their parameters compared
        (a checksum), which data parallelism keeps identical; :class:`RankDrift` where they differ."""
        self.ranks.check_in_step(self.model.params, step)

    def _reads_at(self, before: int, step: int) -> bool:
        """Whether the step from ``before`` to ``step`` ends where the run reads the device anyway
        (logs, evaluation, checkpoint, the end), or ``READ_EVERY`` iterations have passed: --sync-free
        reads its flags there."""
        config = self.config
        return (
            step == config.iters
            or crossed(before, step, config.log_every)
            or (not config.progress and crossed(before, step, 1000))
            or crossed(before, step, config.eval_every)
            or crossed(before, step, config.checkpoint_every)
            or crossed(before, step, READ_EVERY)
        )

    def _show_rewind(self, bar) -> None:
        bar.n = self.step
        bar.refresh()

    def finish(self) -> dict:
        self.save()
        self._raise_pending()  # a signal during that save: the run is saved, stop here
        if not self.scene.test:
            self._peak_memory("train")  # (an evaluation takes it first)
        metrics = self._evaluate(final=True) if self.scene.test else {"views": 0}
        cuda = self.device.type == "cuda"
        held = held_memory(self.device, self.peak_reserved)
        # every process's peak and held memory, in one exchange
        peaks, helds = zip(*self.ranks.all_gather_object((self.peak_memory["train"] / 1e9 if cuda else None, held)))
        result = {
            "test": {k: v for k, v in metrics.items() if k != "per_view"},
            "per_view": metrics.get("per_view", []),
            "num_gaussians": self.num_gaussians,
            "iterations": self.step,
            "train_seconds": self.train_seconds,
            "iterations_per_second": self.step / max(self.train_seconds, 1e-9),
            **refinement_seconds(self.history["strategy"]),
            "peak_gpu_memory_gb": self.peak_memory["train"] / 1e9 if cuda else None,
            "peak_gpu_memory_eval_gb": self.peak_memory["eval"] / 1e9 if cuda and self.scene.test else None,
            **held,
            "device": torch.cuda.get_device_name(self.device) if self.device.type == "cuda" else "cpu",
            "strategy": self.strategy.config(),
            "batch_size": self.config.batch_size,
            "processes": self.ranks.world,
            "peak_gpu_memory_gb_per_process": list(peaks),
            "held_gpu_memory_per_process": list(helds),
        }
        if self.lookahead is not None:
            result["sync_free"] = self.lookahead.summary()
        if self.graphs is not None:
            result["cuda_graph"] = self.graphs.summary()
            if self.gamma_groups is not None:
                result["cuda_graph"].update(self.gamma_groups.summary())
        else:
            result["cuda_graph"] = {"off": self.graph_off}
        result.update(self._result_extras())
        if self.config.dist_balance != "none":
            result["dist_balance"] = {"mode": self.config.dist_balance, "balanced_steps": self.balanced_steps}
        if self.ranks.distributed:
            # every process's, since the wait differs: the slower one waits less
            summaries = self.ranks.all_gather_object(self._communication_summary())
            result["communication"] = mean_communication(summaries, self.ranks.backend)
        if not self.ranks.is_main:
            return result
        outputs.write_json(os.path.join(self.out, outputs.METRICS), result)
        outputs.write_json(os.path.join(self.out, outputs.HISTORY), self.history, indent=None)
        outputs.plot_curves(self.history, os.path.join(self.out, "curves.png"))
        if any("correlation" in entry for entry in self.history["strategy"]):
            label = f"{self.strategy.config()['name']} ({self.config.strategy})"
            outputs.plot_correlation({label: self.history}, os.path.join(self.out, "correlation.png"))
        if self.complexity_maps is not None and self.complexity_maps.computed and self.config.save_maps:
            folder = os.path.join(self.out, "complexity_maps")
            outputs.save_complexity_maps(folder, self.scene.train, self.complexity_maps.all(), self.config.save_maps)
        return result
