"""Frames: when to render each browser's view (:class:`RenderScheduler`), how each mode looks
(colour maps, :func:`depth_image`), and the :class:`RenderLoop` thread that renders a
:class:`~cdcgs.viewer.state.LiveModel` for every connected browser and streams it as a JPEG."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from .cameras import viser_to_pinhole
from .state import LiveModel, Snapshot, Viewable

__all__ = ["RenderLoop", "RenderScheduler", "apply_colormap", "colormap", "depth_image"]

log = logging.getLogger("cdcgs")

GAMMA_REFRESH_SECONDS = 10.0  # during training, Γ (a render of every training view) is renewed at most this often


def colormap(name: str) -> torch.Tensor:
    """[256, 3] float32 lookup table of a matplotlib colour map."""
    import matplotlib

    return torch.from_numpy(matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3]).float()


def apply_colormap(values: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """[..., 3] colours of ``values`` in [0, 1] (clamped) through a [256, 3] table."""
    index = (values.clamp(0.0, 1.0) * 255.0 + 0.5).long()
    return table.to(values.device)[index]


def depth_image(depth: torch.Tensor, alpha: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """[H, W, 3] expected depth through a colour map, near = 0, far = 1 at the 2nd and 98th
    percentiles of the pixels more than half covered, faded by alpha (black where empty)."""
    covered = depth[alpha > 0.5]
    if covered.numel() < 2:
        return torch.zeros(*depth.shape, 3, device=depth.device)
    if covered.numel() > 1_000_000:
        covered = covered[:: covered.numel() // 1_000_000 + 1]
    near, far = torch.quantile(covered, covered.new_tensor([0.02, 0.98])).tolist()
    t = (depth - near) / max(far - near, 1e-6)
    return apply_colormap(1.0 - t, table) * alpha[..., None]


@dataclass(kw_only=True)
class RenderScheduler:
    """When to render one browser's view, and how many pixels high. Pure logic: times in seconds
    from any monotonic clock, passed in.

    A frame is due when the camera or the content (model, mode, resolution cap) differs from the
    last frame's, or when the camera has been still for ``settle_seconds`` since a frame rendered
    below full resolution; never sooner than 1 / ``max_fps`` after the previous one. While the
    camera moves, frames are ``moving_height`` pixels high, which :meth:`rendered` adapts so that
    a frame takes about ``frame_budget_seconds``. With ``render_share`` below 1 (beside a
    training), rendering takes at most that share of the time in the long run: render time is
    spent from a credit that grows by ``render_share`` per second up to ``burst_seconds``, so a
    camera move after a pause is smooth and a long one slows down.
    """

    max_fps: float = 30.0
    settle_seconds: float = 0.3
    frame_budget_seconds: float = 1.0 / 15.0
    min_height: int = 90
    moving_height: int = 360
    render_share: float = 1.0
    burst_seconds: float = 1.0
    _camera: object = None
    _camera_since: float = -math.inf
    _last_frame: tuple | None = None  # (camera, content, full resolution?)
    _last_render_at: float = -math.inf
    _credit: float | None = None  # seconds of rendering allowed now
    _credit_at: float = 0.0

    def next_frame(self, now: float, camera, content, full_height: int) -> int | None:
        """The height to render now (then call :meth:`rendered`), or None for no frame."""
        if camera != self._camera:
            self._camera, self._camera_since = camera, now
        if self._credit is None:
            self._credit = self.burst_seconds
        self._credit = min(self.burst_seconds, self._credit + (now - self._credit_at) * self.render_share)
        self._credit_at = now
        if now - self._last_render_at < 1.0 / self.max_fps or (self.render_share < 1.0 and self._credit <= 0.0):
            return None
        moving = now - self._camera_since < self.settle_seconds
        if (
            self._last_frame is not None
            and self._last_frame[:2] == (camera, content)
            and (self._last_frame[2] or moving)
        ):
            return None
        height = min(self.moving_height, full_height) if moving else full_height
        self._last_frame = (camera, content, height >= full_height)
        self._last_render_at = now
        return height

    def rendered(self, height: int, seconds: float, full_height: int) -> None:
        """Account a frame of ``height`` pixels that took ``seconds``, and adapt the moving
        resolution to it."""
        self._credit = (self.burst_seconds if self._credit is None else self._credit) - seconds
        # Render time grows with the pixel count, the square of the height.
        scale = math.sqrt(self.frame_budget_seconds / max(seconds, 1e-6))
        target = height * min(max(scale, 0.5), 1.5)
        self.moving_height = int(min(max(target, self.min_height), max(full_height, self.min_height)))


class RenderLoop:
    """Renders the current mode of a :class:`LiveModel` for every browser of a viser server.

    One background thread (:meth:`start`) wakes on :attr:`wake` (a camera moved, the model or the
    mode changed) or every 50 ms (so a still camera's frame sharpens), and gives each browser a
    frame when its :class:`RenderScheduler` says one is due. :meth:`render` is one frame, also
    usable without a server. ``say(text)`` shows a message in the page (Γ's progress and failure);
    ``gamma_ready()`` is called once a new Γ is shown.
    """

    def __init__(
        self, viewable: Viewable, model: LiveModel, *, max_height: int, max_fps: float = 30.0, render_share: float = 1.0
    ):
        self.viewable = viewable
        self.model = model
        self.max_height = max_height
        self.max_fps = max_fps
        self.render_share = render_share
        self.mode = "colour"
        self.frames = 0
        self.watched = False  # a browser is connected
        self.frame_seconds: dict[int, float] = {}  # per browser, its last full-resolution frame
        self.last_frame = (0, 0, 0.0)  # width, height, seconds
        self.wake = threading.Event()
        self.say: Callable[[str], None] = lambda _text: None
        self.gamma_ready: Callable[[], None] = lambda: None
        self.gamma: tuple[int, torch.Tensor, Snapshot] | None = None  # (version, Γ, its snapshot)
        self._gamma_at = -math.inf
        self._schedulers: dict[int, RenderScheduler] = {}
        self._tables = {"depth": colormap("viridis"), "complexity": colormap("turbo")}
        self._frame_times: list[float] = []
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    # ---------------------------------------------------------------------------- the thread

    def start(self, server, on_tick: Callable[[], None] = lambda: None) -> None:
        """Render for ``server``'s browsers until :meth:`stop`; ``on_tick()`` after each round."""
        self._stopping.clear()
        self._thread = threading.Thread(target=self._run, args=(server, on_tick), name="cdcgs-viewer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        self.wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None

    def _run(self, server, on_tick) -> None:
        while not self._stopping.is_set():
            self.wake.wait(timeout=0.05)  # the tick lets a still camera's frame sharpen
            self.wake.clear()
            clients = server.get_clients()
            self.watched = bool(clients)
            for client in clients.values():
                try:
                    self.serve(client)
                except Exception:  # one browser's failure (e.g. gone mid-frame) must not stop the others
                    log.exception("viewer: a frame for browser %s failed", client.client_id)
            on_tick()

    def forget(self, client_id: int) -> None:
        """A browser left."""
        self._schedulers.pop(client_id, None)
        self.frame_seconds.pop(client_id, None)

    def frame_rate(self, now: float) -> float:
        """Frames per second sent over the last 2 s, to all browsers together."""
        return sum(1 for t in self._frame_times if now - t < 2.0) / 2.0

    # ---------------------------------------------------------------------------- frames

    def serve(self, client) -> None:
        """Send ``client`` a frame if one is due."""
        camera = client.camera
        if camera.image_height <= 0 or camera.image_width <= 0:
            return
        full_height = min(camera.image_height, self.max_height)
        pose = (tuple(camera.wxyz), tuple(camera.position), camera.fov, camera.image_width, camera.image_height)
        scheduler = self._schedulers.setdefault(
            client.client_id, RenderScheduler(max_fps=self.max_fps, render_share=self.render_share)
        )
        content = (self.model.version, self.mode, self.max_height, self.gamma[0] if self.gamma else None)
        height = scheduler.next_frame(time.monotonic(), pose, content, full_height)
        if height is None:
            return
        start = time.perf_counter()
        image = self.render(camera.wxyz, camera.position, camera.fov, camera.aspect, height)
        seconds = time.perf_counter() - start
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=90 if height >= full_height else 75)
        scheduler.rendered(height, seconds, full_height)
        if height >= full_height:
            self.frame_seconds[client.client_id] = seconds
        self.frames += 1
        now = time.monotonic()
        self._frame_times = [t for t in self._frame_times if now - t < 2.0] + [now]
        self.last_frame = (image.shape[1], image.shape[0], seconds)

    def render(self, wxyz, position, fov: float, aspect: float, height: int) -> np.ndarray:
        """[H, W, 3] uint8 frame of the current mode from a viser camera."""
        from ..render import rasterize

        viewmat, K, width, height = viser_to_pinhole(wxyz, position, fov, aspect, height)
        snapshot, version = self.model.current()
        mode = self.mode
        colors = None
        if mode == "complexity" and not self.viewable.complexity.unavailable:
            snapshot, gamma = self._complexity(snapshot, version)
            colors = apply_colormap(gamma, self._tables["complexity"])
        elif mode == "complexity":
            mode = "colour"
        background = self.viewable.background if mode == "colour" else (0.0, 0.0, 0.0)
        with torch.no_grad():
            image, alpha, info = rasterize(
                **snapshot.render_args(colors),
                viewmat=viewmat,
                K=K,
                width=width,
                height=height,
                background=background,
                antialiased=self.viewable.antialiased,
                render_depth=mode == "depth",
            )
            if mode == "depth":
                image = depth_image(info.depth, alpha, self._tables["depth"])
            elif mode == "alpha":
                image = alpha[..., None].expand(-1, -1, 3)
            return (image.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()

    def _complexity(self, snapshot: Snapshot, version: int) -> tuple[Snapshot, torch.Tensor]:
        """(snapshot, Γ [N]) to show: Γ is computed for the current snapshot (of ``version``), at most every
        ``GAMMA_REFRESH_SECONDS`` during training (it renders every training view), so the
        complexity mode shows the model as of that Γ."""
        complexity = self.viewable.complexity
        now = time.monotonic()
        if self.gamma is None or (self.gamma[0] != version and now - self._gamma_at > GAMMA_REFRESH_SECONDS):
            self.say(f"Computing Γ over {len(complexity.views)} training views…")
            try:
                gamma = complexity.compute(snapshot, self.viewable.antialiased)
            except Exception as err:
                complexity.unavailable = f"computing Γ failed: {err}"
                self.say(f"Complexity is not available: computing Γ failed ({err}); see the terminal.")
                raise
            self.gamma, self._gamma_at = (version, gamma, snapshot), time.monotonic()
            self.gamma_ready()
        return self.gamma[2], self.gamma[1]
