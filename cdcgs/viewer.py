"""A browser viewer for a saved model or a running training: viser serves the page, and every frame
is rendered by :func:`cdcgs.rasterize` on the model's device and streamed as a JPEG.

Each connected browser has its own camera and its own :class:`RenderScheduler`: a frame is rendered
only when the camera or what is shown changed, at most ``max_fps`` times a second, at a lower
resolution while the camera moves (adapted to keep a frame near ``frame_budget_seconds``) and at
full resolution once it has been still for ``settle_seconds``. During training the viewer renders
a :class:`Snapshot` (detached copies of the parameters) that the trainer hands over through
:meth:`Viewer.offer` only while a browser is connected, no more often than every
``refresh_seconds``, and frames take at most ``render_share`` of the time in the long run; an
unwatched training pays one check per step.

Modes: colour (the model's SH colours), depth (expected depth, viridis), alpha (accumulated
opacity) and complexity (CDC-GS's per-Gaussian Γ over the training views, turbo), which exists only
where the training images do.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import socket
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from .errors import InputError

log = logging.getLogger("cdcgs")

MODES = ("colour", "depth", "alpha", "complexity")


# --------------------------------------------------------------------------------------------
# Cameras: viser's (wxyz, position, fov, aspect) and ours (world-to-camera viewmat, K)


def quat_to_matrix(wxyz) -> np.ndarray:
    """[3, 3] rotation of a (w, x, y, z) quaternion (normalised here)."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def matrix_to_quat(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a [3, 3] rotation, w >= 0 (Shepperd's method, stable for any angle)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > max(m[0, 0], m[1, 1], m[2, 2]):
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax([m[0, 0], m[1, 1], m[2, 2]]))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def viser_to_pinhole(wxyz, position, fov: float, aspect: float, height: int) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """(viewmat [4, 4], K [3, 3], width, height) of a viser camera rendered ``height`` pixels high.

    viser's ``wxyz`` and ``position`` are the camera-to-world rotation and the camera centre in the
    OpenCV convention that cdcgs uses too (x right, y down, z forward); ``fov`` is vertical, in
    radians; ``aspect`` is width / height. Square pixels, principal point at the image centre.
    """
    width = max(1, round(height * aspect))
    rotation = quat_to_matrix(wxyz)
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3] = -rotation.T @ np.asarray(position, dtype=np.float64)
    focal = 0.5 * height / math.tan(0.5 * fov)
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return torch.from_numpy(viewmat).float(), torch.from_numpy(K).float(), width, height


def pinhole_to_viser(viewmat, K, height: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz, position, vertical fov in radians) of a world-to-camera ``viewmat`` and intrinsics."""
    viewmat = torch.as_tensor(viewmat).double().numpy()
    rotation = viewmat[:3, :3].T
    position = -rotation @ viewmat[:3, 3]
    fy = float(torch.as_tensor(K)[1, 1])
    return matrix_to_quat(rotation), position, 2.0 * math.atan(0.5 * height / fy)


# --------------------------------------------------------------------------------------------
# What is shown


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


class Complexity:
    """CDC-GS's per-Gaussian complexity Γ over the training views, for the complexity mode.

    Γ of a Gaussian is the max over views and pixels of HF(p) w(p) / w_max(p), as the ``cdc``
    strategy's full schedule computes it; it needs the training images, so a model without them
    gets ``unavailable`` (the reason, shown in the page) instead.
    """

    def __init__(self, views=(), method: str = "dwt", unavailable: str | None = None, device="cpu"):
        self.views = list(views)
        self.method = method
        self.device = torch.device(device)
        self.unavailable = unavailable or (None if self.views else "the model has no training views to measure it on")
        self._maps = None

    def compute(self, snapshot: Snapshot, antialiased: bool = False) -> torch.Tensor:
        """[N] Γ in [0, 1] of every Gaussian of ``snapshot``; 0 where none of its pixels is seen."""
        from .complexity import complexity_map, gaussian_complexity
        from .io.scene import load_images
        from .render import rasterize

        if self.unavailable:
            raise RuntimeError(f"complexity is not available: {self.unavailable}")
        if self._maps is None:
            missing = [view for view in self.views if view.image is None]
            if missing:
                load_images(missing, device=self.device, progress=False)
            self._maps = [complexity_map(view.image, self.method) for view in self.views]
        gamma = torch.zeros(snapshot.num, device=snapshot.means.device)
        with torch.no_grad():
            for view, hf_map in zip(self.views, self._maps):
                _, _, info = rasterize(
                    **snapshot.render_args(), viewmat=view.viewmat, K=view.K, width=view.width, height=view.height, antialiased=antialiased
                )
                torch.maximum(gamma, gaussian_complexity(info, hf_map)[0], out=gamma)
        return gamma


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


# --------------------------------------------------------------------------------------------
# When to render


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
        if self._last_frame is not None and self._last_frame[:2] == (camera, content) and (self._last_frame[2] or moving):
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


@dataclass(kw_only=True)
class LiveModel:
    """The snapshot a viewer shows and its version; during training, when a new one is due.

    A new snapshot re-renders every watching browser's frame, so snapshots are taken at most every
    ``refresh_seconds`` and, where frames are slow (a large model on the CPU), rarely enough that
    those re-renders take at most ``render_share`` of the time.
    """

    snapshot: Snapshot
    refresh_seconds: float = 1.0
    render_share: float = 0.05
    version: int = 0
    taken_at: float = -math.inf

    def due(self, now: float, watched: bool, frame_seconds: float = 0.0) -> bool:
        """A training should hand over a new snapshot: someone watches and this one is old.
        ``frame_seconds``: what the browsers' last frames took to render, together."""
        return watched and now - self.taken_at >= max(self.refresh_seconds, frame_seconds / self.render_share)

    def replace(self, snapshot: Snapshot, now: float) -> None:
        self.snapshot, self.taken_at, self.version = snapshot, now, self.version + 1


# --------------------------------------------------------------------------------------------
# Loading what to show


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

    An output folder also gives the training cameras and images (for the frustums and Γ) when
    its scene can still be loaded from the path in its config.json; otherwise a note says why not.

    Raises:
        InputError: the path is missing, is a folder that is not a cdcgs run (or holds no model
            yet), or a PLY that the importer refuses (its message names what is wrong).
    """
    from .io import load_checkpoint, load_scene, read_ply
    from .train.model import GaussianModel
    from .train.trainer import config_from_dict

    path = os.fspath(path)
    device = torch.device(device)
    if not os.path.exists(path):
        raise InputError(path, "no such file or folder (give a cdcgs output folder or a 3DGS .ply file)")
    if os.path.isfile(path):
        model = GaussianModel.from_ply(read_ply(path), device=device)
        _check_model(model, path)
        reason = "a PLY file holds no training images, which Γ is measured against; open the run's output folder instead"
        return Viewable(Snapshot.of(model), os.path.basename(path), [], Complexity(unavailable=reason))
    config_path = os.path.join(path, "config.json")
    if not os.path.isfile(config_path):
        raise InputError(path, "not a cdcgs output folder (no config.json); to view a PLY, give the .ply file itself")
    try:
        with open(config_path) as f:
            saved = json.load(f)
        config = config_from_dict(saved["train"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(config_path, f"unreadable run configuration ({type(err).__name__}: {err})") from None
    ply_path, checkpoint_path = os.path.join(path, "point_cloud.ply"), os.path.join(path, "checkpoint.pt")
    if os.path.isfile(ply_path):
        model = GaussianModel.from_ply(read_ply(ply_path), device=device)
    elif os.path.isfile(checkpoint_path):
        model = GaussianModel.from_state_dict(load_checkpoint(checkpoint_path)["model"], device=device)
    else:
        raise InputError(path, "holds no model yet (no point_cloud.ply or checkpoint.pt); to watch a training, run it with --view")
    _check_model(model, ply_path if os.path.isfile(ply_path) else checkpoint_path)
    d = config.data
    notes, views = [], []
    try:
        scene = load_scene(d.data, images=d.images, factor=d.factor, test_every=d.test_every, train_on_all=d.train_on_all,
                           skip_missing=d.skip_missing, load_images_now=False)  # fmt: skip
        views = scene.train
        complexity = Complexity(views, method=saved.get("strategy", {}).get("complexity_method", "dwt"), device=device)
    except (InputError, ValueError) as err:
        notes.append(f"training cameras not shown: the run's scene could not be loaded ({err})")
        complexity = Complexity(unavailable=f"the run's training images could not be loaded ({err})")
    background = (1.0, 1.0, 1.0) if config.background == "white" else (0.0, 0.0, 0.0)
    title = os.path.basename(os.path.normpath(path))
    return Viewable(Snapshot.of(model), title, views, complexity, background, config.antialiased, notes)


def _check_model(model, path: str) -> None:
    if model.num == 0:
        raise InputError(path, "holds no Gaussians: there is nothing to show")
    for name, value in model.params.items():
        if not torch.isfinite(value).all():
            raise InputError(path, f"the model's {name} hold NaN or infinite values")


# --------------------------------------------------------------------------------------------
# The server


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
            raise ValueError(f"port must be an int in 0..65535, got {self.port!r}")
        if not self.max_fps > 0:
            raise ValueError(f"max_fps must be positive, got {self.max_fps}")
        if self.max_height is not None and self.max_height < 16:
            raise ValueError(f"max_height must be at least 16 pixels, got {self.max_height}")
        if not self.refresh_seconds >= 0:
            raise ValueError(f"refresh_seconds must be non-negative, got {self.refresh_seconds}")
        if not 0 < self.render_share <= 1:
            raise ValueError(f"render_share must be in (0, 1], got {self.render_share}")


def check_port_free(host: str, port: int) -> None:
    """Raise ValueError naming the address when ``host:port`` cannot be listened on (viser would
    silently move to the next port instead)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as err:
        raise ValueError(f"host {host!r} is not an address of this machine ({err.strerror})") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds
        try:
            probe.bind(address)
        except OSError as err:
            raise ValueError(f"cannot listen on {host}:{port}: {err.strerror}; choose another port (0 picks a free one)") from None


class Viewer:
    """A viser server that renders a model for every connected browser (see the module docs).

    ``start()`` serves it, ``offer(model, step)`` hands a training's current state over when a new
    snapshot is due, ``stop()`` ends it. Renders run on one background thread.
    """

    def __init__(self, viewable: Viewable, settings: ViewerSettings | None = None, *, live: bool = False):
        self.viewable = viewable
        self.settings = settings or ViewerSettings()
        self.live = live
        device = viewable.snapshot.means.device
        self.max_height = self.settings.max_height or (1080 if device.type == "cuda" else 540)
        self.model = LiveModel(
            snapshot=viewable.snapshot, refresh_seconds=self.settings.refresh_seconds, render_share=self.settings.render_share
        )
        self.mode = "colour"
        self.frames = 0
        self.url = None
        self._watched = False
        self._frame_seconds: dict[int, float] = {}  # per browser, its last full-resolution frame
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._schedulers: dict[int, RenderScheduler] = {}
        self._gamma: tuple[int, torch.Tensor, Snapshot] | None = None  # (version, Γ, its snapshot)
        self._gamma_at = -math.inf
        self._tables = {"depth": colormap("viridis"), "complexity": colormap("turbo")}
        self._frame_times: list[float] = []
        self._last_frame = (0, 0, 0.0)  # width, height, seconds
        self._stats_at = -math.inf
        self._server = None
        self._thread = None
        self._mode_note = None
        self._offer_failed = False

    # ---------------------------------------------------------------------------- lifecycle

    def start(self) -> str:
        """Serve the page; returns its URL. Raises ValueError when the address is taken."""
        import viser

        s = self.settings
        check_port_free(s.host, s.port)
        server = viser.ViserServer(host=s.host, port=s.port, label=f"cdcgs · {self.viewable.title}", verbose=False)
        if s.port and server.get_port() != s.port:
            server.stop()
            raise ValueError(f"cannot listen on {s.host}:{s.port}: the port was taken; choose another port")
        self._server = server
        try:
            server.scene.world_axes.visible = False
            self._build_gui(server)
            self._add_cameras(server)
            server.on_client_connect(self._on_connect)
            server.on_client_disconnect(self._on_disconnect)
        except BaseException:
            server.stop()
            self._server = None
            raise
        self._thread = threading.Thread(target=self._loop, name="cdcgs-viewer", daemon=True)
        self._thread.start()
        shown = socket.gethostname() if s.host in ("0.0.0.0", "::", "") else s.host
        self.url = f"http://{f'[{shown}]' if ':' in shown else shown}:{server.get_port()}"
        return self.url

    def stop(self) -> None:
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        if self._server is not None:
            self._server.stop()
            self._server = None

    def offer(self, model, step: int) -> None:
        """Called by a training after each step: takes a :class:`Snapshot` of ``model`` when one
        is due (see :class:`LiveModel`). Cheap otherwise."""
        if self._offer_failed:
            return
        now = time.monotonic()
        if self.model.due(now, self._watched, sum(self._frame_seconds.values())):
            try:
                snapshot = Snapshot.of(model, step)
            except Exception:  # e.g. out of memory for the copy: the training matters more than the view
                self._offer_failed = True
                log.exception("viewer: could not copy the model at step %d; the viewer keeps the last copy and training goes on", step)
                self._say("The training's model could no longer be copied (see the terminal); this is the last copy.")
                return
            with self._lock:
                self.model.replace(snapshot, now)
            self._wake.set()

    # ---------------------------------------------------------------------------- page

    def _build_gui(self, server) -> None:
        gui = server.gui
        self._stats = gui.add_markdown(self._stats_text())
        complexity = self.viewable.complexity
        options = list(MODES) if not complexity.unavailable else [*MODES[:3], "complexity (not available for this model)"]
        self._mode_choice = gui.add_dropdown("Show", options, initial_value="colour", hint="colour, expected depth, alpha, or CDC-GS complexity Γ")
        self._mode_note = gui.add_markdown(self._mode_text("colour"))
        self._height_choice = gui.add_slider(
            "Max height (px)", min=min(90, self.max_height), max=max(2160, self.max_height), step=10, initial_value=self.max_height,
            hint="frames are rendered at most this many pixels high; lower is faster",
        )  # fmt: skip
        self._cameras_choice = gui.add_checkbox("Training cameras", initial_value=True, visible=bool(self.viewable.views))
        for note in self.viewable.notes:
            gui.add_markdown(f"*{note}*")

        @self._mode_choice.on_update
        def _(_event) -> None:
            mode = self._mode_choice.value
            self.mode = "complexity" if mode.startswith("complexity") else mode
            self._say(self._mode_text(self.mode))
            self._wake.set()

        @self._height_choice.on_update
        def _(_event) -> None:
            self.max_height = int(self._height_choice.value)
            self._wake.set()

        @self._cameras_choice.on_update
        def _(_event) -> None:
            for frustum in self._frustums:
                frustum.visible = self._cameras_choice.value

    def _mode_text(self, mode: str) -> str:
        if mode == "depth":
            return "Expected depth: yellow near, purple far (2nd to 98th percentile of this frame)."
        if mode == "alpha":
            return "Accumulated opacity: white opaque, black empty."
        if mode == "complexity":
            complexity = self.viewable.complexity
            if complexity.unavailable:
                return f"**Complexity Γ is not available for this model:** {complexity.unavailable}. Showing colour."
            step = self._gamma[2].step if self.live and self._gamma else None
            when = f", at step {step:,}, renewed at most every 10 s" if step is not None else ""
            return (f"CDC-GS complexity Γ of each Gaussian ({complexity.method}, max over {len(complexity.views)} training views{when}): "
                    "blue flat (0) to red complex (1).")  # fmt: skip
        return "The model's colours."

    def _stats_text(self) -> str:
        snapshot = self.model.snapshot
        step = f" · step {snapshot.step:,}" if snapshot.step is not None else ""
        live = " (training)" if self.live else ""
        now = time.monotonic()
        recent = [t for t in self._frame_times if now - t < 2.0]
        rate = f"**{len(recent) / 2.0:.1f} frames/s**" if recent else "**idle**: a frame is rendered when the view changes"
        width, height, seconds = self._last_frame
        frame = f"  \nlast frame {width} × {height} in {seconds * 1000:.0f} ms" if width else ""
        return f"**{snapshot.num:,} Gaussians**{step}{live}  \n{rate}{frame}"

    def _say(self, text: str) -> None:
        """Show ``text`` under the mode switch (when the page exists)."""
        if self._mode_note is not None:
            self._mode_note.content = text

    def _add_cameras(self, server) -> None:
        """The training cameras as frustums (a click flies there), and the first browser camera:
        the first training camera, or outside the model looking at its middle, y down (COLMAP)."""
        from .io.scene import scene_extent

        self._frustums = []
        views = self.viewable.views
        camera = server.initial_camera
        if not views:
            means = self.model.snapshot.means[:: max(1, self.model.snapshot.num // 100_000)]  # a sample is enough
            center = means.median(dim=0).values
            radius = float((means - center).norm(dim=1).quantile(0.9)) if means.shape[0] > 1 else 1.0
            center = center.double().cpu().numpy()
            camera.up = (0.0, -1.0, 0.0)
            camera.position = center - np.array([0.0, 0.0, 2.5 * max(radius, 1e-3)])
            camera.look_at = center
            return
        size = 0.05 * scene_extent(views)
        poses = [pinhole_to_viser(view.viewmat, view.K, view.height) for view in views]
        for index, (view, (wxyz, position, fov)) in enumerate(zip(views, poses)):
            frustum = server.scene.add_camera_frustum(
                f"/training_cameras/{index:05d}", fov=fov, aspect=view.width / view.height, scale=size,
                thickness=1.5, thickness_units="screen", color=(230, 120, 30), wxyz=wxyz, position=position,
            )  # fmt: skip
            frustum.on_click(self._fly_to(wxyz, position, fov))
            self._frustums.append(frustum)
        wxyz, position, fov = poses[0]
        camera.fov = fov
        camera.position = position
        camera.look_at = position + quat_to_matrix(wxyz)[:, 2] * scene_extent(views)
        camera.up = -np.mean([quat_to_matrix(q)[:, 1] for q, _, _ in poses], axis=0)

    def _fly_to(self, wxyz, position, fov):
        def fly(event) -> None:
            with event.client.atomic():
                event.client.camera.wxyz = wxyz
                event.client.camera.position = position
                event.client.camera.fov = fov

        return fly

    def _on_connect(self, client) -> None:
        client.camera.on_update(lambda _camera: self._wake.set())
        self._wake.set()

    def _on_disconnect(self, client) -> None:
        self._schedulers.pop(client.client_id, None)
        self._frame_seconds.pop(client.client_id, None)

    # ---------------------------------------------------------------------------- rendering

    def _loop(self) -> None:
        while not self._stopping.is_set():
            self._wake.wait(timeout=0.05)  # the tick lets a still camera's frame sharpen
            self._wake.clear()
            clients = self._server.get_clients()
            self._watched = bool(clients)
            for client in clients.values():
                try:
                    self._serve(client)
                except Exception:  # one browser's failure (e.g. gone mid-frame) must not stop the others
                    log.exception("viewer: a frame for browser %s failed", client.client_id)
            now = time.monotonic()
            if now - self._stats_at > 0.5:
                self._stats_at = now
                self._stats.content = self._stats_text()

    def _serve(self, client) -> None:
        camera = client.camera
        if camera.image_height <= 0 or camera.image_width <= 0:
            return
        full_height = min(camera.image_height, self.max_height)
        pose = (tuple(camera.wxyz), tuple(camera.position), camera.fov, camera.image_width, camera.image_height)
        share = self.settings.render_share if self.live else 1.0
        scheduler = self._schedulers.setdefault(client.client_id, RenderScheduler(max_fps=self.settings.max_fps, render_share=share))
        content = (self.model.version, self.mode, self.max_height, self._gamma[0] if self._gamma else None)
        height = scheduler.next_frame(time.monotonic(), pose, content, full_height)
        if height is None:
            return
        start = time.perf_counter()
        image = self.render(camera.wxyz, camera.position, camera.fov, camera.aspect, height)
        seconds = time.perf_counter() - start
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=90 if height >= full_height else 75)
        scheduler.rendered(height, seconds, full_height)
        if height >= full_height:
            self._frame_seconds[client.client_id] = seconds
        self.frames += 1
        now = time.monotonic()
        self._frame_times = [t for t in self._frame_times if now - t < 2.0] + [now]
        self._last_frame = (image.shape[1], image.shape[0], seconds)

    def render(self, wxyz, position, fov: float, aspect: float, height: int) -> np.ndarray:
        """[H, W, 3] uint8 frame of the current mode from a viser camera."""
        from .render import rasterize

        viewmat, K, width, height = viser_to_pinhole(wxyz, position, fov, aspect, height)
        with self._lock:
            snapshot = self.model.snapshot
        mode = self.mode
        colors = None
        if mode == "complexity" and not self.viewable.complexity.unavailable:
            snapshot, gamma = self._complexity(snapshot)
            colors = apply_colormap(gamma, self._tables["complexity"])
        elif mode == "complexity":
            mode = "colour"
        background = self.viewable.background if mode == "colour" else (0.0, 0.0, 0.0)
        with torch.no_grad():
            image, alpha, info = rasterize(
                **snapshot.render_args(colors), viewmat=viewmat, K=K, width=width, height=height,
                background=background, antialiased=self.viewable.antialiased, render_depth=mode == "depth",
            )  # fmt: skip
            if mode == "depth":
                image = depth_image(info.depth, alpha, self._tables["depth"])
            elif mode == "alpha":
                image = alpha[..., None].expand(-1, -1, 3)
            return (image.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()

    def _complexity(self, snapshot: Snapshot) -> tuple[Snapshot, torch.Tensor]:
        """(snapshot, Γ [N]) to show: Γ is computed for the current snapshot, at most every 10 s
        during training (it renders every training view), so the complexity mode shows the model
        as of that Γ."""
        now = time.monotonic()
        if self._gamma is None or (self._gamma[0] != self.model.version and now - self._gamma_at > 10.0):
            self._say(f"Computing Γ over {len(self.viewable.complexity.views)} training views…")
            try:
                gamma = self.viewable.complexity.compute(snapshot, self.viewable.antialiased)
            except Exception as err:
                self.viewable.complexity = Complexity(unavailable=f"computing Γ failed: {err}")
                self._say(f"Complexity is not available: computing Γ failed ({err}); see the terminal.")
                raise
            self._gamma, self._gamma_at = (self.model.version, gamma, snapshot), time.monotonic()
            self._say(self._mode_text("complexity"))
        return self._gamma[2], self._gamma[1]


def serve(viewer: Viewer) -> None:
    """Start ``viewer``, say where it is, and serve until Ctrl-C."""
    url = viewer.start()
    print(f"cdcgs view: {viewer.viewable.snapshot.num:,} Gaussians at {url} (Ctrl-C to stop)", flush=True)
    if viewer.settings.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"cdcgs view: listening on {viewer.settings.host}: other machines can open it", flush=True)
    for note in viewer.viewable.notes:
        print(f"cdcgs view: {note}", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()


def training_viewer(trainer, settings: ViewerSettings) -> Viewer:
    """A started viewer of a :class:`~cdcgs.train.trainer.Trainer`'s model (``cdcgs train --view``):
    its training cameras, Γ over its training images, snapshots handed over by ``Viewer.offer``."""
    config = trainer.config
    views = trainer.scene.train
    method = trainer.strategy.config().get("complexity_method", "dwt")
    viewable = Viewable(
        Snapshot.of(trainer.model, trainer.step), os.path.basename(os.path.normpath(config.out)), views,
        Complexity(views, method, device=trainer.device), tuple(trainer.fixed_background.tolist()), config.antialiased,
    )  # fmt: skip
    viewer = Viewer(viewable, settings, live=True)
    url = viewer.start()
    print(f"cdcgs train: watch the training at {url}", flush=True)
    return viewer
