"""Training configuration as nested dataclasses; the CLI is generated from their fields' help."""

from __future__ import annotations

from dataclasses import dataclass, field

from .model import LearningRates


def option(default, help: str, **kwargs):
    """A dataclass field with a help line for the command line."""
    if isinstance(default, (list, dict)) or callable(default):
        return field(default_factory=default if callable(default) else (lambda: default), metadata={"help": help, **kwargs})
    return field(default=default, metadata={"help": help, **kwargs})


@dataclass(kw_only=True)
class DataConfig:
    """Where the scene is and how it is split."""

    data: str = option("", "scene folder: COLMAP (sparse/0 + images*) or one with transforms.json")
    images: str | None = option(None, "COLMAP image folder, e.g. images_4 (its suffix is the downsampling factor)")
    factor: int | None = option(None, "downsampling factor (images_{factor}, or resize on load when that folder is missing)")
    test_every: int = option(8, "hold out every n-th image by sorted name for testing (0: none)")
    train_on_all: bool = option(False, "train on every image (the held-out ones are still evaluated)")
    skip_missing: bool = option(False, "skip views whose image file is missing instead of refusing the scene")


@dataclass(kw_only=True)
class TrainConfig:
    """One training run."""

    data: DataConfig = option(DataConfig, "the scene")
    out: str = option("outputs/run", "output folder (metrics.json, renders, PLY, checkpoint)")
    strategy: str = option("adc", "densification strategy (see README: adc, absgs, 3dgs, cdc, ...)")
    iters: int = option(30_000, "training iterations")
    device: str = option("auto", "torch device: cuda, cuda:1, cpu, or auto (cuda when there is one)")
    seed: int = option(0, "seed of every random draw: same seed, same device, same run")
    background: str = option("black", "background colour: black, white or random (a new colour each iteration)")
    sh_degree: int = option(3, "highest spherical-harmonics degree (raised by one every --sh-every steps)")
    sh_every: int = option(1000, "iterations between spherical-harmonics degree increases")
    ssim_weight: float = option(0.2, "loss = (1 - w) L1 + w (1 - SSIM), SSIM with an 11 px Gaussian window")
    init_opacity: float = option(0.1, "opacity of the initial Gaussians")
    scale_rule: str = option("3dgs", "initial scales from the 3 nearest neighbours: 3dgs (arithmetic mean) or cdc (geometric)")
    antialiased: bool = option(False, "Mip-Splatting opacity compensation in the rasterizer")
    lr: LearningRates = option(LearningRates, "learning rates")
    eval_every: int = option(7000, "evaluate on the test views every n iterations (and at the end; 0: only at the end)")
    checkpoint_every: int = option(5000, "write checkpoint.pt every n iterations (and at the end; 0: only at the end)")
    log_every: int = option(50, "iterations between points of the loss/PSNR/#Gaussians curves")
    save_renders: bool = option(True, "save each test view as ground truth | render | error map")
    resume: bool = option(False, "continue the run in --out from its checkpoint.pt")
    overwrite: bool = option(False, "replace a finished or interrupted run already in --out (otherwise refused)")
    progress: bool = option(True, "show a progress bar")
    view: bool = option(False, "serve a browser viewer of the model while it trains (as cdcgs view; renders only while a browser watches)")
    view_port: int = option(8080, "port of the --view viewer (0: any free port)")
    view_host: str = option("127.0.0.1", "address the --view viewer listens on; 0.0.0.0 lets other machines open it")

    def __post_init__(self):
        if self.iters <= 0:
            raise ValueError(f"iters must be positive, got {self.iters}")
        if self.background not in ("black", "white", "random"):
            raise ValueError(f"background must be black, white or random, got {self.background!r}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0.0 <= self.ssim_weight <= 1.0:
            raise ValueError(f"ssim_weight must be in [0, 1], got {self.ssim_weight}")
        if not 0.0 < self.init_opacity < 1.0:
            raise ValueError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        if self.scale_rule not in ("3dgs", "cdc"):
            raise ValueError(f"scale_rule must be 3dgs or cdc, got {self.scale_rule!r}")
        for name in ("sh_every", "log_every"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive")
        if not 0 <= self.view_port <= 65535:
            raise ValueError(f"view_port must be in 0..65535, got {self.view_port}")
        for name in ("eval_every", "checkpoint_every"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be non-negative")
