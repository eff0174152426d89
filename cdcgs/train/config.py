"""Training configuration as nested dataclasses; the CLI is generated from their fields' help.

Imports no kernel and no torch: the command line and run folders read it cheaply.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from ..errors import OptionError
from .presets import PRESET_TRAINING, PRESETS, TRAINING_DEFAULTS, canonical_name

__all__ = [
    "BACKGROUNDS",
    "DIST_MODES",
    "OPTIMIZERS",
    "RESOLUTION_SCHEDULES",
    "DataConfig",
    "LearningRates",
    "TrainConfig",
    "background_color",
    "batch_rule",
    "config_from_dict",
    "config_to_dict",
    "option",
    "resolve_defaults",
]

BACKGROUNDS = ("black", "white", "random")
SCALE_RULES = ("3dgs", "cdc")
OPTIMIZERS = ("adam", "selective", "torch-adam")
RESOLUTION_SCHEDULES = ("none", "dash")
DIST_MODES = ("data", "shards")


def option(
    default,
    help: str,
    *,
    choices: tuple | None = None,
    metavar: str | None = None,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
):
    """A dataclass field with a help line (and, for a closed set, its choices; for the usage line,
    a name for its value; for a number, its range [low, high], or (low, high] with ``low_open``)
    for the command line and :func:`check_values`."""
    metadata = {"help": help}
    if choices is not None:
        metadata["choices"] = tuple(choices)
    if metavar is not None:
        metadata["metavar"] = metavar
    if low is not None or high is not None:
        metadata["range"] = (low, high, low_open)
    if isinstance(default, (list, dict)) or callable(default):
        return field(default_factory=default if callable(default) else (lambda: default), metadata=metadata)
    return field(default=default, metadata=metadata)


def check_values(instance, flag_prefix: str = "") -> None:
    """Raise OptionError, naming the command-line flag, for a field outside its ``choices``, or a
    number that is not finite or outside its ``range``."""
    for f in dataclasses.fields(instance):
        value = getattr(instance, f.name)
        flag = "--" + (flag_prefix + f.name).replace("_", "-")
        choices = f.metadata.get("choices")
        if choices is not None and value is not None and value not in choices:
            raise OptionError(f"{flag} must be one of {', '.join(map(str, choices))}, got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise OptionError(f"{flag} must be a finite number, got {value}")
        bounds = f.metadata.get("range")
        if bounds is not None and value is not None:
            low, high, low_open = bounds
            below = low is not None and (value <= low if low_open else value < low)
            if below or (high is not None and value > high):
                opening = "(" if low_open else "["
                interval = f"{opening}{'-inf' if low is None else low}, {'inf' if high is None else high}]"
                raise OptionError(f"{flag} must be in {interval}, got {value}")


@dataclass(kw_only=True)
class DataConfig:
    """Where the scene is and how it is split."""

    data: str = option("", "scene folder: COLMAP (sparse/0 + images*) or one with transforms.json", metavar="DIR")
    images: str | None = option(
        None, "COLMAP image folder, e.g. images_4 (its suffix is the downsampling factor)", metavar="NAME"
    )
    factor: int | None = option(
        None, "downsampling factor (images_{factor}, or resize on load when that folder is missing)"
    )
    test_every: int = option(8, "hold out every n-th image by sorted name for testing (0: none)")
    train_on_all: bool = option(False, "train on every image (the held-out ones are still evaluated)")
    test_views: str | None = option(
        None,
        "hold out the images named in FILE (one per line, e.g. another run's test_views.txt) instead of every n-th: "
        "the same test photos for two models of one capture",
        metavar="FILE",
    )
    skip_missing: bool = option(False, "skip views whose image file is missing instead of refusing the scene")
    random_init: bool = option(
        False, "a COLMAP model without 3D points starts from random points in the cameras' common view (else refused)"
    )

    def scene_options(self) -> dict:
        """The keyword arguments of :func:`cdcgs.io.load_scene` that this configuration sets."""
        return dict(
            images=self.images,
            factor=self.factor,
            test_every=self.test_every,
            train_on_all=self.train_on_all,
            test_views=self.test_views,
            skip_missing=self.skip_missing,
            random_init=self.random_init,
        )


@dataclass(kw_only=True)
class LearningRates:
    """Adam learning rates per parameter (the CDC-GS code's). Position rates are x scene extent."""

    means_init: float = option(1.6e-4, "position learning rate at the start, x scene extent", low=0.0, low_open=True)
    means_final: float = option(
        1.6e-6, "position learning rate at the end (exponential decay), x scene extent", low=0.0, low_open=True
    )
    log_scales: float = option(5e-3, "learning rate of the log scales", low=0.0)
    quats: float = option(1e-3, "learning rate of the rotations (quaternions)", low=0.0)
    opacity_logits: float | None = option(
        None,
        "learning rate of the opacity logits (none: the strategy's, 0.025 as the CDC-GS and current INRIA code; 0.05 for 3DGS-MCMC, as 3DGS's first release)",
        low=0.0,
    )
    sh_dc: float = option(2.5e-3, "learning rate of the degree-0 spherical-harmonics coefficients", low=0.0)
    sh_rest: float = option(2.5e-3 / 20, "learning rate of the higher spherical-harmonics coefficients", low=0.0)

    def __post_init__(self):
        check_values(self, "lr_")


@dataclass(kw_only=True)
class TrainConfig:
    """One training run."""

    data: DataConfig = field(default_factory=DataConfig, metadata={"help": "scene"})
    out: str = option("outputs/run", "output folder (metrics.json, renders, PLY, checkpoint)", metavar="DIR")
    strategy: str = option("3dgs", "densification strategy preset (docs/cdc-gs.md)", choices=tuple(PRESETS))
    iters: int = option(30_000, "training iterations", low=1)
    device: str = option("auto", "torch device: cuda, cuda:1, cpu, or auto (cuda when there is one)", metavar="DEVICE")
    seed: int = option(0, "seed of every random draw: same seed, same device, same run")
    background: str = option("black", "background colour (random: a new colour each iteration)", choices=BACKGROUNDS)
    sh_degree: int = option(
        3, "highest spherical-harmonics degree (raised by one every --sh-every steps)", low=0, high=3
    )
    sh_every: int = option(1000, "iterations between spherical-harmonics degree increases", low=1)
    ssim_weight: float = option(
        0.2, "loss = (1 - w) L1 + w (1 - SSIM), SSIM with an 11 px Gaussian window", low=0.0, high=1.0
    )
    init_opacity: float | None = option(
        None,
        "opacity of the initial Gaussians, in (0, 1) (none: the strategy's, 0.1, or 0.5 for 3DGS-MCMC)",
        low=0.0,
        high=1.0,
        low_open=True,
    )
    scale_rule: str | None = option(
        None,
        "initial scales from the 3 nearest neighbours: cdc (geometric mean, the CDC-GS code) or 3dgs (arithmetic) (none: the strategy's, cdc; 3dgs for 3DGS-MCMC)",
        choices=SCALE_RULES,
    )
    init_scale: float | None = option(
        None,
        "factor on the initial scales (none: the strategy's, 1; 0.1 for 3DGS-MCMC)",
        low=0.0,
        low_open=True,
    )
    antialiased: bool = option(False, "Mip-Splatting opacity compensation in the rasterizer")
    fused_loss: bool = option(
        True,
        "the loss as Warp kernels, two passes forward and two backward (off: kornia's SSIM and torch's L1, the same loss in about 60 torch kernels)",
    )
    optimizer: str | None = option(
        None,
        "adam (one Warp launch for all parameters), selective: Adam on the Gaussians the step's view sees only, the others keep their parameters and moments (Taming 3DGS's selective Adam; not exact), or torch-adam: torch's Adam, fused on CUDA, one launch per parameter (the reference adam replaced) (none: the preset's, adam; selective for fast)",
        choices=OPTIMIZERS,
    )
    resolution_schedule: str | None = option(
        None,
        "none, or dash: DashGaussian's schedule, low resolution first, raised with the photos' frequency content until densification ends, and the position learning rate's decay held until half resolution (none: the preset's, none; dash for fast)",
        choices=RESOLUTION_SCHEDULES,
    )
    sync_free: bool = option(
        False,
        "render a view into slots sized by its last count of pairs instead of reading the count, so the host never waits for the GPU between the reads a training makes anyway (logs, densification, evaluation); a render that overflows its slots halts every update until the next read, which takes the iterations from it again: the same run as without (on several processes a halt stops every process, and all go back together; adam or selective)",
    )
    cuda_graph: bool | None = option(
        None,
        "--sync-free, and each step between two refinements replayed as one CUDA graph (captured again after a refinement, a new SH degree or a larger count), so the host only picks the view and the rates: the same training, about 0.74x the time of bonsai's 3dgs on an H100; on the CPU the same steps run one operation at a time (a --batch-size that the processes divide, on several processes with the step's all-reduce in the graph; views of one size; a fixed background; adam or selective; not with --complexity-schedule online; not with --view) (none: as the resumed run chose, else on wherever the training can take it on CUDA and off elsewhere, saying why)",
    )
    batch_size: int = option(
        1,
        "training views per step, their gradients averaged (over all processes of a torchrun launch); the schedules count views, so B views per step take 1/B of the steps",
        low=1,
    )
    batch_lr_scale: float | None = option(
        None,
        "factor on every learning rate at --batch-size B (none: sqrt(B), Grendel-GS's rule)",
        low=0.0,
        low_open=True,
    )
    batch_eps_scale: float | None = option(
        None, "factor on Adam's eps at --batch-size B (none: 1/sqrt(B))", low=0.0, low_open=True
    )
    batch_beta_power: float | None = option(
        None, "Adam's betas raised to this power at --batch-size B (none: B)", low=0.0, low_open=True
    )
    dist_mode: str = option(
        "data",
        "how the processes of a torchrun launch share the scene: data (data parallelism: every process holds every Gaussian and the step's gradients are all-reduced) or shards (each process holds a slice of the Gaussians, with its gradients and Adam moments, and renders its views of the whole scene through an exchange of the projected slices; 3dgs, absgs and CDC-GS's full schedule without caps of the count, adam or torch-adam; its steps replayed as CUDA graphs as data parallelism's: docs/distributed.md)",
        choices=DIST_MODES,
    )
    dist_backend: str = option(
        "auto",
        "torch.distributed backend of a torchrun launch: auto (nccl when every process has a GPU of its own, else gloo), nccl or gloo",
        choices=("auto", "nccl", "gloo"),
    )
    dist_exchange: str = option(
        "gradients",
        "what the processes of a torchrun launch exchange each step: gradients (every parameter's, in one all-reduce) or colours (the geometric parameters' gradients, and each view's colour gradients, from which every process rebuilds the spherical harmonics' gradients of the whole batch: 3.8x fewer bytes on 2 GPUs, 3.2x on 4, for one SH adjoint more per view of the step)",
        choices=("gradients", "colours"),
    )
    dist_balance: str = option(
        "none",
        "which process renders which views of a step in a torchrun launch: none (positions rank, rank + processes, ...) or counts (the views split by their last intersection counts, the costliest first to the least loaded process, so that the processes reach the all-reduce together; where every view of the step has a count that all processes know, with --sync-free or the replayed steps, and at least two views per process; the same views and gradients, summed in another order; not with --dist-exchange colours)",
        choices=("none", "counts"),
    )
    dist_timeout: float = option(
        600.0,
        "seconds a process of a torchrun launch waits for the others in a collective before the run stops with an error",
        low=1.0,
    )
    check_ranks_every: int = option(
        1000,
        "iterations between comparisons of the processes' parameters in a torchrun launch (0: never); a difference stops the run",
        low=0,
    )
    lr: LearningRates = field(default_factory=LearningRates, metadata={"help": "learning rates"})
    eval_every: int = option(
        7000, "evaluate on the test views every n iterations (and at the end; 0: only at the end)", low=0
    )
    checkpoint_every: int = option(
        5000, "write checkpoint.pt every n iterations (and at the end; 0: only at the end)", low=0
    )
    log_every: int = option(50, "iterations between points of the loss/PSNR/#Gaussians curves", low=1)
    save_renders: bool = option(True, "save each test view as ground truth | render | error map")
    save_maps: int = option(
        4,
        "complexity maps of the first n training views as PNGs in complexity_maps/ (strategies that measure complexity)",
        low=0,
    )
    resume: bool = option(False, "continue the run in --out from its checkpoint.pt")
    overwrite: bool = option(False, "replace a finished or interrupted run already in --out (otherwise refused)")
    progress: bool = option(True, "show a progress bar")

    def __post_init__(self):
        check_values(self)
        if self.init_opacity == 1.0:  # its logit is infinite
            raise OptionError("--init-opacity must be in (0, 1), got 1.0")


def batch_rule(config: TrainConfig) -> tuple[float, float, float]:
    """(learning-rate factor, eps factor, beta power) of ``config``'s batch size: sqrt(B), 1/sqrt(B)
    and B (Grendel-GS: B views per step as B steps of one view, to first order), each replaced by
    its option when set."""
    b = config.batch_size
    return (
        math.sqrt(b) if config.batch_lr_scale is None else config.batch_lr_scale,
        1.0 / math.sqrt(b) if config.batch_eps_scale is None else config.batch_eps_scale,
        float(b) if config.batch_beta_power is None else config.batch_beta_power,
    )


def resolve_defaults(config: TrainConfig, strategy, saved: dict | None = None) -> TrainConfig:
    """``config`` with every option left at none (``init_opacity``, ``scale_rule``, ``init_scale``,
    ``lr.opacity_logits``, ``optimizer``, ``resolution_schedule``, ``cuda_graph``) set to the value of the run
    being resumed (``saved``, its :func:`config_to_dict`), else to its preset's
    (:data:`cdcgs.train.presets.PRESET_TRAINING`), else to ``strategy``'s (its
    ``training_defaults`` dict), else to :data:`cdcgs.train.presets.TRAINING_DEFAULTS`: a resumed
    run goes on with what it started with, also when the defaults changed in between."""
    saved = saved or {}
    defaults = {
        "init_opacity": saved.get("init_opacity"),
        "scale_rule": saved.get("scale_rule"),
        "init_scale": saved.get("init_scale"),
        "opacity_lr": saved.get("lr", {}).get("opacity_logits"),
        "optimizer": saved.get("optimizer"),
        "resolution_schedule": saved.get("resolution_schedule"),
    }
    preset = {**TRAINING_DEFAULTS, **strategy.training_defaults, **PRESET_TRAINING.get(config.strategy, {})}
    defaults = {k: preset[k] if v is None else v for k, v in defaults.items()}
    lr = config.lr
    if lr.opacity_logits is None:
        lr = dataclasses.replace(lr, opacity_logits=defaults["opacity_lr"])
    # Steps replayed as CUDA graphs: left at none, as the resumed run chose (runs before this
    # default saved false, and go on without them); a new run decides where it trains.
    cuda_graph = saved.get("cuda_graph") if config.cuda_graph is None else config.cuda_graph
    return dataclasses.replace(
        config,
        lr=lr,
        cuda_graph=cuda_graph,
        **{
            name: defaults[name] if getattr(config, name) is None else getattr(config, name)
            for name in ("init_opacity", "scale_rule", "init_scale", "optimizer", "resolution_schedule")
        },
    )


def config_to_dict(config: TrainConfig) -> dict:
    """The configuration as JSON-ready nested dicts (config.json, checkpoints)."""
    return dataclasses.asdict(config)


# Fields that earlier versions wrote and that no longer configure a training: the viewer of
# `train --view` is a command-line option now.
_RETIRED_FIELDS = ("view", "view_port", "view_host")


def config_from_dict(data: dict) -> TrainConfig:
    """A :class:`TrainConfig` from :func:`config_to_dict`'s output, also as earlier versions wrote it.

    Raises:
        ValueError: a field this version does not know, or a value it refuses.
    """
    data = {k: v for k, v in data.items() if k not in _RETIRED_FIELDS}
    data["data"] = DataConfig(**data.get("data", {}))
    data["lr"] = LearningRates(**data.get("lr", {}))
    if "strategy" in data:
        data["strategy"] = canonical_name(data["strategy"])
    try:
        return TrainConfig(**data)
    except TypeError as err:  # an unknown field
        raise OptionError(f"not a configuration of this cdcgs version: {err}") from None


def background_color(name: str) -> tuple[float, float, float] | None:
    """RGB in [0, 1] of a ``background`` option; None for ``random`` (drawn each iteration)."""
    colors = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "random": None}
    if name not in colors:
        raise OptionError(f"background must be one of {', '.join(BACKGROUNDS)}, got {name!r}")
    return colors[name]
