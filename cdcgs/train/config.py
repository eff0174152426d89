"""Training configuration as nested dataclasses; the CLI is generated from their fields' help.

Imports no kernel and no torch: the command line and run folders read it cheaply.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ..errors import OptionError
from .presets import PRESETS, canonical_name

__all__ = [
    "BACKGROUNDS",
    "DataConfig",
    "LearningRates",
    "TrainConfig",
    "background_color",
    "config_from_dict",
    "config_to_dict",
    "option",
]

BACKGROUNDS = ("black", "white", "random")
SCALE_RULES = ("3dgs", "cdc")


def option(default, help: str, *, choices: tuple | None = None, metavar: str | None = None):
    """A dataclass field with a help line (and, for a closed set, its choices; for the usage line,
    a name for its value) for the command line."""
    metadata = {"help": help}
    if choices is not None:
        metadata["choices"] = tuple(choices)
    if metavar is not None:
        metadata["metavar"] = metavar
    if isinstance(default, (list, dict)) or callable(default):
        return field(default_factory=default if callable(default) else (lambda: default), metadata=metadata)
    return field(default=default, metadata=metadata)


def check_choices(instance) -> None:
    """Raise ValueError for a field whose value is outside its ``choices``."""
    for f in dataclasses.fields(instance):
        choices = f.metadata.get("choices")
        if choices is not None and getattr(instance, f.name) not in choices:
            raise OptionError(
                f"{f.name} must be one of {', '.join(map(str, choices))}, got {getattr(instance, f.name)!r}"
            )


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
    skip_missing: bool = option(False, "skip views whose image file is missing instead of refusing the scene")


@dataclass(kw_only=True)
class LearningRates:
    """Adam learning rates per parameter (3DGS defaults). Position rates are x scene extent."""

    means_init: float = option(1.6e-4, "position learning rate at the start, x scene extent")
    means_final: float = option(1.6e-6, "position learning rate at the end (exponential decay), x scene extent")
    log_scales: float = option(5e-3, "learning rate of the log scales")
    quats: float = option(1e-3, "learning rate of the rotations (quaternions)")
    opacity_logits: float = option(5e-2, "learning rate of the opacity logits")
    sh_dc: float = option(2.5e-3, "learning rate of the degree-0 spherical-harmonics coefficients")
    sh_rest: float = option(2.5e-3 / 20, "learning rate of the higher spherical-harmonics coefficients")


@dataclass(kw_only=True)
class TrainConfig:
    """One training run."""

    data: DataConfig = field(default_factory=DataConfig, metadata={"help": "scene"})
    out: str = option("outputs/run", "output folder (metrics.json, renders, PLY, checkpoint)", metavar="DIR")
    strategy: str = option("3dgs", "densification strategy preset (docs/cdc-gs.md)", choices=tuple(PRESETS))
    iters: int = option(30_000, "training iterations")
    device: str = option("auto", "torch device: cuda, cuda:1, cpu, or auto (cuda when there is one)", metavar="DEVICE")
    seed: int = option(0, "seed of every random draw: same seed, same device, same run")
    background: str = option("black", "background colour (random: a new colour each iteration)", choices=BACKGROUNDS)
    sh_degree: int = option(3, "highest spherical-harmonics degree (raised by one every --sh-every steps)")
    sh_every: int = option(1000, "iterations between spherical-harmonics degree increases")
    ssim_weight: float = option(0.2, "loss = (1 - w) L1 + w (1 - SSIM), SSIM with an 11 px Gaussian window")
    init_opacity: float = option(0.1, "opacity of the initial Gaussians")
    scale_rule: str = option(
        "3dgs",
        "initial scales from the 3 nearest neighbours: 3dgs (arithmetic mean) or cdc (geometric)",
        choices=SCALE_RULES,
    )
    antialiased: bool = option(False, "Mip-Splatting opacity compensation in the rasterizer")
    lr: LearningRates = field(default_factory=LearningRates, metadata={"help": "learning rates"})
    eval_every: int = option(7000, "evaluate on the test views every n iterations (and at the end; 0: only at the end)")
    checkpoint_every: int = option(5000, "write checkpoint.pt every n iterations (and at the end; 0: only at the end)")
    log_every: int = option(50, "iterations between points of the loss/PSNR/#Gaussians curves")
    save_renders: bool = option(True, "save each test view as ground truth | render | error map")
    save_maps: int = option(
        4,
        "complexity maps of the first n training views as PNGs in complexity_maps/ (strategies that measure complexity)",
    )
    resume: bool = option(False, "continue the run in --out from its checkpoint.pt")
    overwrite: bool = option(False, "replace a finished or interrupted run already in --out (otherwise refused)")
    progress: bool = option(True, "show a progress bar")

    def __post_init__(self):
        check_choices(self)
        if self.iters <= 0:
            raise OptionError(f"iters must be positive, got {self.iters}")
        if not 0 <= self.sh_degree <= 3:
            raise OptionError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0.0 <= self.ssim_weight <= 1.0:
            raise OptionError(f"ssim_weight must be in [0, 1], got {self.ssim_weight}")
        if not 0.0 < self.init_opacity < 1.0:
            raise OptionError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        for name in ("sh_every", "log_every"):
            if getattr(self, name) <= 0:
                raise OptionError(f"{name} must be positive")
        for name in ("eval_every", "checkpoint_every", "save_maps"):
            if getattr(self, name) < 0:
                raise OptionError(f"{name} must be non-negative")


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
