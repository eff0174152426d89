"""The run folder: what a training writes (config, metrics, history, plots, complexity maps) and
how a finished or interrupted run is read back (:func:`load_run`, for eval, render, export and the
viewer).

Layout of ``OUT``: config.json, test_views.txt (the held-out image names, for ``--test-views``),
checkpoint.pt, point_cloud.ply, metrics.json, history.json, curves.png, correlation.png
(strategies that log Γ-Ψ correlation), complexity_maps/*.png, test_renders/*.png.
"""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass, field

import torch

from ..errors import InputError
from ..io import load_checkpoint, load_scene, read_ply
from .config import TrainConfig, config_from_dict
from .model import GaussianModel

__all__ = [
    "CHECKPOINT",
    "CONFIG",
    "PLY",
    "TEST_VIEWS",
    "Run",
    "RunLock",
    "correlation_curve",
    "load_run",
    "plot_correlation",
    "plot_curves",
    "save_complexity_maps",
    "view_stem",
    "write_json",
    "write_view_names",
]

CONFIG, CHECKPOINT, PLY = "config.json", "checkpoint.pt", "point_cloud.ply"
METRICS, HISTORY = "metrics.json", "history.json"
TEST_VIEWS = "test_views.txt"
LOCK = ".lock"


class RunLock:
    """The lock of a run folder: while a training (or a resume) holds it, no other can start there.

    Taken atomically (the lock file is created exclusively) and holds the owner's pid, host and
    start time. A lock left by a process of this host that no longer exists is stale: it is
    reported (``stale`` names it) and taken over. Use as a context manager.

    Raises (on entering):
        InputError: another live process (or a process of another host, which cannot be checked)
            holds the folder; the message names it.
    """

    def __init__(self, folder: str):
        self.path = os.path.join(folder, LOCK)
        self.stale: dict | None = None

    def __enter__(self) -> RunLock:
        import socket
        import time

        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%d %H:%M:%S")}
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = self._holder()
                if (
                    holder.get("host") == me["host"]
                    and isinstance(holder.get("pid"), int)
                    and not _alive(holder["pid"])
                ):
                    self.stale = holder
                    os.remove(self.path)
                    continue
                raise InputError(
                    os.path.dirname(self.path),
                    f"is in use by another training (pid {holder.get('pid')} on {holder.get('host')}, started "
                    f"{holder.get('started')}); wait for it, or choose another --out. If that process is gone "
                    f"(another machine's cannot be checked from here), delete {self.path}",
                ) from None
            with os.fdopen(fd, "w") as f:
                json.dump(me, f)
            return self
        raise InputError(os.path.dirname(self.path), "could not take the run folder's lock")

    def __exit__(self, *exc) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.remove(self.path)

    def _holder(self) -> dict:
        try:
            with open(self.path) as f:
                holder = json.load(f)
            return holder if isinstance(holder, dict) else {}
        except (OSError, ValueError):
            return {}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def view_stem(name: str) -> str:
    """A file name stem for a view's image name (folders flattened)."""
    return os.path.splitext(name.replace(os.sep, "_"))[0]


def write_view_names(path: str, views) -> None:
    """The views' image names, one per line (what ``--test-views`` reads back), written atomically."""
    _write_atomically(path, "".join(f"{v.name}\n" for v in views))


def write_json(path: str, data, indent: int | None = 2) -> None:
    """Write ``data`` as JSON to ``path`` atomically: an interrupted write leaves the old file."""
    _write_atomically(path, json.dumps(data, indent=indent))


def _write_atomically(path: str, text: str) -> None:
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


@dataclass
class Run:
    """A run folder read back: its configuration, the strategy it recorded, and its model.

    ``model_path`` is the file the Gaussians came from (the PLY, else the checkpoint).
    """

    path: str
    config: TrainConfig
    strategy: dict
    model: GaussianModel
    model_path: str
    notes: list[str] = field(default_factory=list)

    def load_scene(self, device="cpu", *, load_images: bool = True, progress: bool = False):
        """The run's scene, from the path its configuration names. A run trained with
        ``--test-views`` holds out the names it recorded (its own test_views.txt): the file it was
        given may have moved or changed since.

        Raises:
            InputError: the scene is no longer where the run found it, or is unreadable.
        """
        d = self.config.data
        options = d.scene_options()
        own = os.path.join(self.path, TEST_VIEWS)
        if d.test_views is not None and os.path.isfile(own):
            options["test_views"] = own
        return load_scene(d.data, device=device, load_images_now=load_images, progress=progress, **options)


def load_run(path, device="cpu") -> Run:
    """Read the run in folder ``path``: config.json and the model (point_cloud.ply, else the
    checkpoint's Gaussians at their highest SH degree).

    Raises:
        InputError: no such folder, not a cdcgs run folder, an unreadable configuration, or no
            model yet.
    """
    path = os.fspath(path)
    if not os.path.isdir(path):
        raise InputError(path, "no such run folder")
    config_path = os.path.join(path, CONFIG)
    if not os.path.isfile(config_path):
        raise InputError(path, "not a cdcgs output folder (no config.json)")
    try:
        with open(config_path) as f:
            saved = json.load(f)
        config = config_from_dict(saved["train"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(config_path, f"unreadable run configuration ({type(err).__name__}: {err})") from None
    device = torch.device(device)
    ply_path, checkpoint_path = os.path.join(path, PLY), os.path.join(path, CHECKPOINT)
    if os.path.isfile(ply_path):
        model, model_path = GaussianModel.from_ply(read_ply(ply_path), device=device), ply_path
    elif os.path.isfile(checkpoint_path):
        model = GaussianModel.from_state_dict(load_checkpoint(checkpoint_path)["model"], device=device)
        model.sh_degree = model.max_sh_degree
        model_path = checkpoint_path
    else:
        raise InputError(path, "holds no model yet (no point_cloud.ply or checkpoint.pt)")
    if model.nonfinite():
        raise InputError(model_path, f"the model's {', '.join(model.nonfinite())} hold NaN or infinite values")
    strategy = saved.get("strategy", {})
    return Run(
        path=path,
        config=config,
        strategy=strategy if isinstance(strategy, dict) else {},
        model=model,
        model_path=model_path,
    )


def save_complexity_maps(folder: str, views, maps, count: int) -> None:
    """The complexity maps of the first ``count`` views as grey PNGs in ``folder``."""
    from PIL import Image

    os.makedirs(folder, exist_ok=True)
    for view, hf_map in list(zip(views, maps))[:count]:
        Image.fromarray(hf_map.cpu().numpy()).save(os.path.join(folder, f"{view_stem(view.name)}.png"))


# The complexity-density statistics of a densification step (cdcgs.train.cdc.correlations), with
# the axis label of each; runs of earlier versions logged only the first.
CORRELATION_KEYS = {
    "correlation": "Pearson r(Γ, Ψ) (Fig. 4)",
    "correlation_log_density": "Pearson r(Γ, log Ψ)",
    "correlation_rank": "Spearman ρ(Γ, Ψ)",
    "saturated_density": "share of Ψ ≥ 5e5",
}


def correlation_curve(history: dict, key: str = "correlation") -> tuple[list[int], list[float]]:
    """(steps, values) of statistic ``key`` (:data:`CORRELATION_KEYS`) at the densification steps
    that logged it."""
    points = [(e["step"], e[key]) for e in history["strategy"] if key in e]
    return [p[0] for p in points], [p[1] for p in points]


def plot_correlation(histories: dict, path: str) -> None:
    """The complexity-density statistics at each densification step, one panel each (the first
    is CDC-GS's Fig. 4b), for every run of ``histories`` (label -> history)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in CORRELATION_KEYS if any(correlation_curve(h, k)[0] for h in histories.values())]
    fig, axes = plt.subplots(1, len(keys), figsize=(4.6 * len(keys), 3.8), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for label, history in histories.items():
            steps, values = correlation_curve(history, key)
            ax.plot(steps, values, label=label)
        ax.set(title=CORRELATION_KEYS[key], xlabel="iteration")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle("complexity and density of the Gaussians at each densification step")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_curves(history: dict, path: str) -> None:
    """Loss, PSNR (training, smoothed; test at each evaluation) and #Gaussians over iterations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    steps = history["step"]
    axes[0].plot(steps, history["loss"], color="tab:blue")
    axes[0].set(title="training loss", xlabel="iteration", yscale="log")
    axes[1].plot(steps, history["psnr"], color="tab:blue", label="train (smoothed)")
    if history["eval"]:
        evals = history["eval"]
        axes[1].plot([e["step"] for e in evals], [e["psnr"] for e in evals], "o-", color="tab:red", label="test")
    axes[1].set(title="PSNR (dB)", xlabel="iteration")
    axes[1].legend()
    axes[2].plot(steps, history["gaussians"], color="tab:green")
    axes[2].set(title="Gaussians", xlabel="iteration")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
