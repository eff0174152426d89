"""A browser viewer for a saved model or a running training: viser serves the page, and every frame
is rendered by :func:`cdcgs.rasterize` on the model's device and streamed as a JPEG.

Each connected browser has its own camera and its own :class:`RenderScheduler`: a frame is rendered
only when the camera or what is shown changed, at most ``max_fps`` times a second, at a lower
resolution while the camera moves (adapted to keep a frame near ``frame_budget_seconds``) and at
full resolution once it has been still for ``settle_seconds``. During training the viewer renders
a :class:`Snapshot` (detached copies of the parameters) that the trainer hands over through
:meth:`Viewer.offer` (the :class:`TrainingViewer` callback) only while a browser is connected, no
more often than every ``refresh_seconds``, and frames take at most ``render_share`` of the time in
the long run; an unwatched training pays one check per step.

Modes: colour (the model's SH colours), depth (expected depth, viridis), alpha (accumulated
opacity) and complexity (CDC-GS's per-Gaussian Γ over the training views, as the run's strategy
measures it, turbo), which exists only where the training images do.

Modules: ``cameras`` (viser's cameras and cdcgs's), ``state`` (what is shown, loading it),
``render_loop`` (when and how frames are rendered), ``ui`` (the control panel and the training
cameras), ``server`` (the viser server, ``cdcgs view``, ``cdcgs train --view``).
"""

from .cameras import matrix_to_quat, pinhole_to_viser, viser_to_pinhole
from .render_loop import RenderLoop, RenderScheduler
from .server import TrainingViewer, Viewer, ViewerSettings, check_port_free, serve, training_viewer
from .state import Complexity, LiveModel, Snapshot, Viewable, load_viewable
from .ui import MODES

__all__ = [
    "MODES",
    "Complexity",
    "LiveModel",
    "RenderLoop",
    "RenderScheduler",
    "Snapshot",
    "TrainingViewer",
    "Viewable",
    "Viewer",
    "ViewerSettings",
    "check_port_free",
    "load_viewable",
    "matrix_to_quat",
    "pinhole_to_viser",
    "serve",
    "training_viewer",
    "viser_to_pinhole",
]
