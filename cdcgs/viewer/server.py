"""The viser server: :class:`Viewer` (start, stop, hand a training's model over), its
:class:`ViewerSettings`, :func:`check_port_free`, :func:`serve` for ``cdcgs view``, and
:class:`TrainingViewer`, the trainer callback of ``cdcgs train --view``."""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass

from ..errors import OptionError
from .render_loop import RenderLoop
from .state import Complexity, LiveModel, Snapshot, Viewable
from .ui import Panel

__all__ = ["TrainingViewer", "Viewer", "ViewerSettings", "check_port_free", "serve", "training_viewer"]

log = logging.getLogger("cdcgs")


@dataclass(kw_only=True)
class ViewerSettings:
    """Where the viewer listens and how hard it works."""

    host: str = "127.0.0.1"  # loopback only; 0.0.0.0 opens it to other machines
    port: int = 8080  # 0: any free port
    max_fps: float = 30.0  # frames per second per browser, at most
    max_height: int | None = None  # frame height cap in pixels; None: 1080 on CUDA, 540 on the CPU
    refresh_seconds: float = 1.0  # during training: age of the snapshot before a new one is taken
    render_share: float = 0.05  # during training: at most this share of the time rendering (per browser)

    def __post_init__(self):
        if isinstance(self.port, bool) or not isinstance(self.port, int) or not 0 <= self.port <= 65535:
            raise OptionError(f"port must be an int in 0..65535, got {self.port!r}")
        if not self.max_fps > 0:
            raise OptionError(f"max_fps must be positive, got {self.max_fps}")
        if self.max_height is not None and self.max_height < 16:
            raise OptionError(f"max_height must be at least 16 pixels, got {self.max_height}")
        if not self.refresh_seconds >= 0:
            raise OptionError(f"refresh_seconds must be non-negative, got {self.refresh_seconds}")
        if not 0 < self.render_share <= 1:
            raise OptionError(f"render_share must be in (0, 1], got {self.render_share}")


def check_port_free(host: str, port: int) -> None:
    """Raise OptionError naming the address when ``host:port`` cannot be listened on (viser would
    silently move to the next port instead)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as err:
        raise OptionError(f"host {host!r} is not an address of this machine ({err.strerror})") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds
        try:
            probe.bind(address)
        except OSError as err:
            message = f"cannot listen on {host}:{port}: {err.strerror}; choose another port (0 picks a free one)"
            raise OptionError(message) from None


class Viewer:
    """A viser server that renders a model for every connected browser (see the package docs).

    ``start()`` serves it, ``offer(model, step)`` hands a training's current state over when a new
    snapshot is due, ``stop()`` ends it. Frames are rendered by :attr:`renderer`, a
    :class:`~cdcgs.viewer.render_loop.RenderLoop` on one background thread.
    """

    def __init__(self, viewable: Viewable, settings: ViewerSettings | None = None, *, live: bool = False):
        self.viewable = viewable
        self.settings = settings or ViewerSettings()
        self.live = live
        s = self.settings
        device = viewable.snapshot.means.device
        self.model = LiveModel(
            snapshot=viewable.snapshot, refresh_seconds=s.refresh_seconds, render_share=s.render_share
        )
        self.renderer = RenderLoop(
            viewable,
            self.model,
            max_height=s.max_height or (1080 if device.type == "cuda" else 540),
            max_fps=s.max_fps,
            render_share=s.render_share if live else 1.0,
        )
        self.renderer.say = self._say
        self.renderer.gamma_ready = self._gamma_ready
        self.url = None
        self._server = None
        self._panel = None
        self._offer_failed = False

    def start(self) -> str:
        """Serve the page; returns its URL. Raises OptionError when the address is taken."""
        import viser

        s = self.settings
        check_port_free(s.host, s.port)
        server = viser.ViserServer(host=s.host, port=s.port, label=f"cdcgs · {self.viewable.title}", verbose=False)
        if s.port and server.get_port() != s.port:
            server.stop()
            raise OptionError(f"cannot listen on {s.host}:{s.port}: the port was taken; choose another port")
        self._server = server
        try:
            server.scene.world_axes.visible = False
            self._panel = Panel(server, self.viewable, self.renderer, live=self.live)
            server.on_client_connect(self._on_connect)
            server.on_client_disconnect(lambda client: self.renderer.forget(client.client_id))
        except BaseException:
            server.stop()
            self._server = None
            raise
        self.renderer.start(server, on_tick=self._panel.refresh)
        shown = socket.gethostname() if s.host in ("0.0.0.0", "::", "") else s.host
        self.url = f"http://{f'[{shown}]' if ':' in shown else shown}:{server.get_port()}"
        return self.url

    def stop(self) -> None:
        self.renderer.stop()
        if self._server is not None:
            self._server.stop()
            self._server = None

    def offer(self, model, step: int) -> None:
        """Called by a training after each step: takes a :class:`Snapshot` of ``model`` when one
        is due (see :class:`~cdcgs.viewer.state.LiveModel`). Cheap otherwise."""
        if self._offer_failed:
            return
        now = time.monotonic()
        if self.model.due(now, self.renderer.watched, sum(self.renderer.frame_seconds.values())):
            try:
                snapshot = Snapshot.of(model, step)
            except Exception:  # e.g. out of memory for the copy: the training matters more than the view
                self._offer_failed = True
                log.exception(
                    "viewer: could not copy the model at step %d; the viewer keeps the last copy and training goes on",
                    step,
                )
                self._say("The training's model could no longer be copied (see the terminal); this is the last copy.")
                return
            self.model.replace(snapshot, now)
            self.renderer.wake.set()

    def _say(self, text: str) -> None:
        """Show ``text`` under the mode switch (when the page exists)."""
        if self._panel is not None:
            self._panel.say(text)

    def _gamma_ready(self) -> None:
        if self._panel is not None:
            self._panel.say(self._panel.mode_text("complexity"))

    def _on_connect(self, client) -> None:
        client.camera.on_update(lambda _camera: self.renderer.wake.set())
        self.renderer.wake.set()


def serve(viewer: Viewer) -> None:
    """Start ``viewer``, say where it is, and serve until Ctrl-C (SIGINT) or SIGTERM. The handlers
    are in place before the address is printed: a signal sent as soon as it appears stops cleanly."""
    with _stop_on_signals():
        try:
            url = viewer.start()
            print(f"cdcgs view: {viewer.viewable.snapshot.num:,} Gaussians at {url} (Ctrl-C to stop)", flush=True)
            if viewer.settings.host not in ("127.0.0.1", "localhost", "::1"):
                print(f"cdcgs view: listening on {viewer.settings.host}: other machines can open it", flush=True)
            for note in viewer.viewable.notes:
                print(f"cdcgs view: {note}", flush=True)
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
        finally:
            viewer.stop()


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


class _stop_on_signals:
    """SIGINT and SIGTERM stop :func:`serve` cleanly, whatever their handlers were: a process
    started in the background of a script inherits SIGINT ignored, and would never stop on it
    (``cdcgs train`` handles both the same way). Only in the main thread, where Python runs
    signal handlers; the handlers from before are put back on leaving."""

    def __enter__(self):
        self.previous = {}
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self.previous[s] = signal.signal(s, _raise_interrupt)
        return self

    def __exit__(self, *exc):
        for s, handler in self.previous.items():
            signal.signal(s, handler)
        return False


def training_viewer(trainer, settings: ViewerSettings) -> Viewer:
    """A started viewer of a :class:`~cdcgs.train.trainer.Trainer`'s model: its training cameras,
    Γ over its training images as its strategy measures it; snapshots come through
    :meth:`Viewer.offer`."""
    from ..train.config import background_color

    config = trainer.config
    views = trainer.scene.train
    viewable = Viewable(
        Snapshot.of(trainer.model, trainer.step),
        os.path.basename(os.path.normpath(config.out)),
        views,
        Complexity.of_strategy(views, trainer.strategy.config(), trainer.device),
        background_color(config.background) or (0.0, 0.0, 0.0),  # random: black
        config.antialiased,
    )
    viewer = Viewer(viewable, settings, live=True)
    url = viewer.start()
    print(f"cdcgs train: watch the training at {url}", flush=True)
    return viewer


class TrainingViewer:
    """The trainer callback of ``cdcgs train --view``: serves a viewer of the model being trained
    from ``on_start``, hands it the model after each step, stops it at the end (also on an error
    or an interrupt). ``viewer``: the started :class:`Viewer`, or None."""

    # Its renders run on another thread during the training: no steps replayed as CUDA graphs
    # (their captures would take the viewer's launches in; cdcgs.train.graph.graph_refusal).
    renders_beside_training = True

    def __init__(self, settings: ViewerSettings | None = None):
        self.settings = settings or ViewerSettings()
        self.viewer: Viewer | None = None

    def on_start(self, trainer) -> None:
        self.viewer = training_viewer(trainer, self.settings)

    def on_step(self, trainer) -> None:
        if self.viewer is not None:
            self.viewer.offer(trainer.model, trainer.step)

    def on_end(self, trainer) -> None:
        if self.viewer is not None:
            self.viewer.stop()
