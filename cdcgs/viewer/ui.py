"""The page around the frames: the control panel (mode switch, resolution cap, statistics, notes)
and the training cameras drawn as frustums that a click flies to."""

from __future__ import annotations

import math
import time

import numpy as np

from .cameras import camera_rotation, pinhole_to_viser
from .render_loop import GAMMA_REFRESH_SECONDS, RenderLoop
from .state import Complexity, Snapshot, Viewable

__all__ = ["MODES", "Panel", "mode_text", "stats_text"]

MODES = ("colour", "depth", "alpha", "complexity")


def mode_text(mode: str, complexity: Complexity, gamma_step: int | None = None) -> str:
    """The line under the mode switch that says what ``mode`` shows; ``gamma_step``: the training
    step of the snapshot that Γ was measured on, during a training."""
    if mode == "depth":
        return "Expected depth: yellow near, purple far (2nd to 98th percentile of this frame)."
    if mode == "alpha":
        return "Accumulated opacity: white opaque, black empty."
    if mode == "complexity":
        if complexity.unavailable:
            return f"**Complexity Γ is not available for this model:** {complexity.unavailable}. Showing colour."
        when = (
            f", at step {gamma_step:,}, renewed at most every {GAMMA_REFRESH_SECONDS:.0f} s"
            if gamma_step is not None
            else ""
        )
        return (
            f"CDC-GS complexity Γ of each Gaussian ({complexity.method}, {complexity.pixel_aggregation} over pixels, "
            f"{complexity.view_aggregation} over {len(complexity.views)} training views{when}): blue flat (0) to red complex (1)."
        )
    return "The model's colours."


def stats_text(snapshot: Snapshot, live: bool, frame_rate: float, last_frame: tuple[int, int, float]) -> str:
    """The statistics at the top of the panel: Gaussians, training step, frames per second (0:
    idle) and the last frame's size and render time (``last_frame``: width, height, seconds)."""
    step = f" · step {snapshot.step:,}" if snapshot.step is not None else ""
    training = " (training)" if live else ""
    rate = f"**{frame_rate:.1f} frames/s**" if frame_rate else "**idle**: a frame is rendered when the view changes"
    width, height, seconds = last_frame
    frame = f"  \nlast frame {width} × {height} in {seconds * 1000:.0f} ms" if width else ""
    return f"**{snapshot.num:,} Gaussians**{step}{training}  \n{rate}{frame}"


class Panel:
    """The GUI of a viser server for a :class:`RenderLoop`: builds it, and sets the loop's mode and
    resolution cap from it. ``live``: the model is a training's."""

    def __init__(self, server, viewable: Viewable, renderer: RenderLoop, *, live: bool = False):
        self.viewable = viewable
        self.renderer = renderer
        self.live = live
        self._stats_at = -math.inf
        self._frustums: list = []
        gui = server.gui
        self._stats = gui.add_markdown(self.stats())
        complexity = viewable.complexity
        options = (
            list(MODES) if not complexity.unavailable else [*MODES[:3], "complexity (not available for this model)"]
        )
        self._mode_choice = gui.add_dropdown(
            "Show", options, initial_value="colour", hint="colour, expected depth, alpha, or CDC-GS complexity Γ"
        )
        self._mode_note = gui.add_markdown(self.mode_text("colour"))
        max_height = renderer.max_height
        self._height_choice = gui.add_slider(
            "Max height (px)",
            min=min(90, max_height),
            max=max(2160, max_height),
            step=10,
            initial_value=max_height,
            hint="frames are rendered at most this many pixels high; lower is faster",
        )
        self._cameras_choice = gui.add_checkbox("Training cameras", initial_value=True, visible=bool(viewable.views))
        for note in viewable.notes:
            gui.add_markdown(f"*{note}*")

        @self._mode_choice.on_update
        def _(_event) -> None:
            mode = self._mode_choice.value
            renderer.mode = "complexity" if mode.startswith("complexity") else mode
            self.say(self.mode_text(renderer.mode))
            renderer.wake.set()

        @self._height_choice.on_update
        def _(_event) -> None:
            renderer.max_height = int(self._height_choice.value)
            renderer.wake.set()

        @self._cameras_choice.on_update
        def _(_event) -> None:
            for frustum in self._frustums:
                frustum.visible = self._cameras_choice.value

        self._frustums = add_cameras(server, viewable.views, renderer.model.snapshot)

    def mode_text(self, mode: str) -> str:
        gamma = self.renderer.gamma
        return mode_text(mode, self.viewable.complexity, gamma[2].step if self.live and gamma else None)

    def stats(self) -> str:
        renderer = self.renderer
        return stats_text(
            renderer.model.snapshot, self.live, renderer.frame_rate(time.monotonic()), renderer.last_frame
        )

    def refresh(self) -> None:
        """Renew the statistics, at most twice a second."""
        now = time.monotonic()
        if now - self._stats_at > 0.5:
            self._stats_at = now
            self._stats.content = self.stats()

    def say(self, text: str) -> None:
        """Show ``text`` under the mode switch."""
        self._mode_note.content = text


def add_cameras(server, views: list, snapshot: Snapshot) -> list:
    """The training cameras as frustums (a click flies there), and the first browser camera: the
    first training camera, or outside the model looking at its middle, y down (COLMAP). Returns the
    frustums."""
    from ..io import scene_extent

    camera = server.initial_camera
    if not views:
        means = snapshot.means[:: max(1, snapshot.num // 100_000)]  # a sample is enough
        center = means.median(dim=0).values
        radius = float((means - center).norm(dim=1).quantile(0.9)) if means.shape[0] > 1 else 1.0
        center = center.double().cpu().numpy()
        camera.up = (0.0, -1.0, 0.0)
        camera.position = center - np.array([0.0, 0.0, 2.5 * max(radius, 1e-3)])
        camera.look_at = center
        return []
    frustums = []
    size = 0.05 * scene_extent(views)
    poses = [pinhole_to_viser(view.viewmat, view.K, view.height) for view in views]
    for index, (view, (wxyz, position, fov)) in enumerate(zip(views, poses, strict=True)):
        frustum = server.scene.add_camera_frustum(
            f"/training_cameras/{index:05d}",
            fov=fov,
            aspect=view.width / view.height,
            scale=size,
            thickness=1.5,
            thickness_units="screen",
            color=(230, 120, 30),
            wxyz=wxyz,
            position=position,
        )
        frustum.on_click(_fly_to(wxyz, position, fov))
        frustums.append(frustum)
    wxyz, position, fov = poses[0]
    camera.fov = fov
    camera.position = position
    camera.look_at = position + camera_rotation(wxyz)[:, 2] * scene_extent(views)
    camera.up = -np.mean([camera_rotation(q)[:, 1] for q, _, _ in poses], axis=0)
    return frustums


def _fly_to(wxyz, position, fov):
    def fly(event) -> None:
        with event.client.atomic():
            event.client.camera.wxyz = wxyz
            event.client.camera.position = position
            event.client.camera.fov = fov

    return fly
