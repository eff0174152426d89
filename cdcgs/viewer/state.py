"""What the viewer shows: a model's :class:`Snapshot`, the :class:`LiveModel` that a training
refreshes, the :class:`Complexity` Γ of the model over its training views, and
:func:`load_viewable`, which reads a run folder (through :func:`cdcgs.train.outputs.load_run`) or a
3DGS PLY file."""

from __future__ import annotations

import dataclasses
import math
import os
import threading
from dataclasses import dataclass

import torch

from ..errors import InputError

__all__ = ["Complexity", "LiveModel", "Snapshot", "Viewable", "load_viewable"]


@dataclass(frozen=True)
class Snapshot:
    """Detached render inputs of a model at one moment, as :func:`cdcgs.rasterize` takes them.

    means [N, 3]; quats [N, 4] (w, x, y, z); scales [N, 3] (not log); opacities [N] (after the
    sigmoid); sh [N, K, 3] truncated to ``sh_degree``. ``step``: the training iteration, if any.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    sh_degree: int
    step: int | None = None

    @classmethod
    def of(cls, model, step: int | None = None) -> Snapshot:
        """Copies of a :class:`~cdcgs.train.model.GaussianModel`'s current state (no autograd)."""
        with torch.no_grad():
            args = model.render_args()
            rest = args.pop("sh_rest", None)
            if rest is not None:  # one coefficient tensor, truncated to the degree (a copy anyway)
                count = (args["sh_degree"] + 1) ** 2
                args["sh"] = torch.cat([args["sh"], rest], dim=1)[:, :count]
            return cls(**{k: v.detach().clone() if torch.is_tensor(v) else v for k, v in args.items()}, step=step)

    @property
    def num(self) -> int:
        return self.means.shape[0]

    def render_args(self, colors: torch.Tensor | None = None) -> dict:
        args = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "step"}
        if colors is not None:
            del args["sh"], args["sh_degree"]
            args["colors"] = colors
        return args


@dataclass(kw_only=True)
class LiveModel:
    """The snapshot a viewer shows and its version; during training, when a new one is due.

    A new snapshot re-renders every watching browser's frame, so snapshots are taken at most every
    ``refresh_seconds`` and, where frames are slow (a large model on the CPU), rarely enough that
    those re-renders take at most ``render_share`` of the time. :meth:`replace` (the training's
    thread) and :meth:`current` (the viewer's) hold a lock, so the two always agree.
    """

    snapshot: Snapshot
    refresh_seconds: float = 1.0
    render_share: float = 0.05
    version: int = 0
    taken_at: float = -math.inf
    _lock: threading.Lock = dataclasses.field(default_factory=threading.Lock, repr=False, compare=False)

    def due(self, now: float, watched: bool, frame_seconds: float = 0.0) -> bool:
        """A training should hand over a new snapshot: someone watches and this one is old.
        ``frame_seconds``: what the browsers' last frames took to render, together."""
        return watched and now - self.taken_at >= max(self.refresh_seconds, frame_seconds / self.render_share)

    def replace(self, snapshot: Snapshot, now: float) -> None:
        with self._lock:
            self.snapshot, self.taken_at, self.version = snapshot, now, self.version + 1

    def current(self) -> tuple[Snapshot, int]:
        """(snapshot, version), read together."""
        with self._lock:
            return self.snapshot, self.version


class Complexity:
    """CDC-GS's per-Gaussian complexity Γ over the training views, for the complexity mode.

    Γ is what the run's ``cdc`` strategy measures (:func:`cdcgs.complexity.complexity_over_views`):
    per view HF(p) w(p) / w_max(p) aggregated over the pixels by ``pixel_aggregation``, then over
    the views by ``view_aggregation`` ("max" or "mean"), with ``w_max`` as the run had it
    (:data:`cdcgs.complexity.W_MAX_RULES`; runs older than the option used "weight"). The maps of the views are computed on
    first use and kept (:class:`cdcgs.complexity.ComplexityMaps`, which loads the images). A model
    without training views gets ``unavailable`` (the reason, shown in the page) instead.
    """

    def __init__(
        self,
        views=(),
        method: str = "dwt",
        device="cpu",
        *,
        pixel_aggregation: str = "max",
        view_aggregation: str = "max",
        w_max: str = "alpha",
        unavailable: str | None = None,
    ):
        self.views = list(views)
        self.method = method
        self.pixel_aggregation = pixel_aggregation
        self.view_aggregation = view_aggregation
        self.w_max = w_max
        self.unavailable = unavailable or (None if self.views else "the model has no training views to measure it on")
        self.maps = None
        if self.unavailable:
            return
        from ..complexity import AGGREGATIONS, W_MAX_RULES, ComplexityMaps

        for name, value, known in (
            ("pixel_aggregation", pixel_aggregation, AGGREGATIONS),
            ("view_aggregation", view_aggregation, AGGREGATIONS),
            ("w_max", w_max, W_MAX_RULES),
        ):
            if value not in known:
                self.unavailable = f"the run's {name} {value!r} is not one of {', '.join(known)}"
                return
        try:
            self.maps = ComplexityMaps(self.views, method, device)
        except ValueError as err:  # a complexity method this version does not know
            self.unavailable = str(err)

    @classmethod
    def of_strategy(cls, views, strategy: dict, device) -> Complexity:
        """Γ as the strategy whose recorded options are ``strategy`` measures it (the ``strategy``
        entry of a run's config.json, or ``Strategy.config()``)."""
        return cls(
            views,
            strategy.get("complexity_method", "dwt"),
            device,
            pixel_aggregation=strategy.get("pixel_aggregation", "max"),
            view_aggregation=strategy.get("view_aggregation", "max"),
            w_max=strategy.get("w_max", "weight"),
        )

    def compute(self, snapshot: Snapshot, antialiased: bool = False) -> torch.Tensor:
        """[N] Γ in [0, 1] of every Gaussian of ``snapshot``; 0 where none of its pixels is seen."""
        from ..complexity import complexity_over_views
        from ..render import prepare_camera, start_bin_view

        if self.unavailable:
            raise RuntimeError(f"complexity is not available: {self.unavailable}")
        args = snapshot.render_args()
        shape = {key: args[key] for key in ("means", "quats", "scales", "opacities")}

        def bins(index: int):
            view = self.views[index]
            camera = prepare_camera(view.viewmat, view.K, view.width, view.height)
            return start_bin_view(**shape, camera=camera, antialiased=antialiased)

        return complexity_over_views(
            bins,
            self.maps,
            snapshot.num,
            snapshot.means.device,
            pixel_aggregation=self.pixel_aggregation,
            view_aggregation=self.view_aggregation,
            w_max=self.w_max,
        )


@dataclass
class Viewable:
    """A model and what the viewer knows about it."""

    snapshot: Snapshot
    title: str
    views: list  # training views (cameras; images loaded on demand), possibly empty
    complexity: Complexity
    background: tuple = (0.0, 0.0, 0.0)
    antialiased: bool = False
    notes: list = dataclasses.field(default_factory=list)


def load_viewable(path, device) -> Viewable:
    """The model of a cdcgs output folder or of a 3DGS PLY file, on ``device``.

    An output folder also gives the training cameras and images (for the frustums and Γ, measured
    as its recorded strategy measures it) when its scene can still be loaded from the path in its
    config.json; otherwise a note says why not.

    Raises:
        InputError: the path is missing, is a folder that is not a cdcgs run (or holds no model
            yet), or a PLY that the importer refuses (its message names what is wrong).
    """
    from ..io import read_ply
    from ..train.config import background_color
    from ..train.model import GaussianModel
    from ..train.outputs import CHECKPOINT, CONFIG, PLY, load_run

    path = os.fspath(path)
    device = torch.device(device)
    if not os.path.exists(path):
        raise InputError(path, "no such file or folder (give a cdcgs output folder or a 3DGS .ply file)")
    if os.path.isfile(path):
        model = GaussianModel.from_ply(read_ply(path), device=device)
        _check_model(model, path)
        reason = (
            "a PLY file holds no training images, which Γ is measured against; open the run's output folder instead"
        )
        return Viewable(Snapshot.of(model), os.path.basename(path), [], Complexity(unavailable=reason))
    try:
        run = load_run(path, device)
    except InputError as err:  # the folder's own problems get advice; its files' are as they are
        if err.path == path and not os.path.isfile(os.path.join(path, CONFIG)):
            raise InputError(path, f"{err.problem}; to view a PLY, give the .ply file itself") from None
        if err.path == path and not any(os.path.isfile(os.path.join(path, name)) for name in (PLY, CHECKPOINT)):
            raise InputError(path, f"{err.problem}; to watch a training, run it with --view") from None
        raise
    _check_model(run.model, run.model_path)
    notes, views = [], []
    try:
        views = run.load_scene(device, load_images=False).train
    except (InputError, ValueError) as err:
        notes.append(f"training cameras not shown: the run's scene could not be loaded ({err})")
        complexity = Complexity(unavailable=f"the run's training images could not be loaded ({err})")
    else:
        complexity = Complexity.of_strategy(views, run.strategy, device)
    background = background_color(run.config.background) or (0.0, 0.0, 0.0)  # random: black
    title = os.path.basename(os.path.normpath(path))
    return Viewable(Snapshot.of(run.model), title, views, complexity, background, run.config.antialiased, notes)


def _check_model(model, path: str) -> None:
    if model.num == 0:
        raise InputError(path, "holds no Gaussians: there is nothing to show")
    for name, value in model.params.items():
        if not torch.isfinite(value).all():
            raise InputError(path, f"the model's {name} hold NaN or infinite values")
