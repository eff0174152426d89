"""The viewer without a browser: camera conversion, render scheduling, snapshots, the frames of each
mode, loading what to show, and the errors of `cdcgs view` (the browser test is test_viewer_e2e.py)."""

import itertools
import json
import math
import shutil
import socket
import types

import numpy as np
import pytest
import torch
from conftest import look_at, make_scene, test_devices

from cdcgs.cli import main as cli_main
from cdcgs.complexity import complexity_map, gaussian_complexity
from cdcgs.datasets.procedural import make_procedural_scene
from cdcgs.errors import InputError
from cdcgs.geometry import quat_to_rotation
from cdcgs.io import GaussianPly, write_ply
from cdcgs.render import rasterize
from cdcgs.train.config import DataConfig, TrainConfig
from cdcgs.train.model import GaussianModel
from cdcgs.train.trainer import Trainer
from cdcgs.viewer import (
    Complexity,
    LiveModel,
    RenderLoop,
    RenderScheduler,
    Snapshot,
    TrainingViewer,
    Viewable,
    Viewer,
    ViewerSettings,
    load_viewable,
    matrix_to_quat,
    pinhole_to_viser,
    viser_to_pinhole,
)
from cdcgs.viewer.ui import mode_text

DEFAULT_DEVICE = test_devices()[0]


def read_json(path):
    with open(path) as f:
        return json.load(f)


def write_json(path, data) -> None:
    with open(path, "w") as f:
        json.dump(data, f)


# ------------------------------------------------------------------------------------ cameras


def test_identity_camera_by_hand():
    viewmat, K, width, height = viser_to_pinhole((1.0, 0.0, 0.0, 0.0), (1.0, 2.0, 3.0), math.pi / 2, 1.5, 100)
    assert (width, height) == (150, 100)
    expected_view = torch.tensor([[1.0, 0, 0, -1], [0, 1, 0, -2], [0, 0, 1, -3], [0, 0, 0, 1]])
    torch.testing.assert_close(viewmat, expected_view)
    # Vertical fov 90 degrees: fy = (H / 2) / tan(45 degrees) = 50; principal point at the centre.
    torch.testing.assert_close(K, torch.tensor([[50.0, 0, 75], [0, 50, 50], [0, 0, 1]]))


def test_rotated_camera_by_hand():
    # 90 degrees about world y: the camera's z (forward) becomes world +x, its x (right) world -z.
    half = math.sqrt(0.5)
    viewmat, K, _, _ = viser_to_pinhole((half, 0.0, half, 0.0), (0.0, 0.0, 0.0), 2 * math.atan(0.5), 1.0, 64)
    torch.testing.assert_close(viewmat[:3, :3], torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]), atol=1e-7, rtol=0)
    torch.testing.assert_close(K, torch.tensor([[64.0, 0, 32], [0, 64, 32], [0, 0, 1]]))
    # World (5, 0, 0) is 5 ahead on the optical axis; (5, 1, -1) is 1 right and 1 down of it.
    cam = viewmat @ torch.tensor([[5.0, 0, 0, 1], [5.0, 1, -1, 1]]).T
    torch.testing.assert_close(cam[:3].T, torch.tensor([[0.0, 0, 5], [1, 1, 5]]), atol=1e-6, rtol=0)
    pixels = (K @ cam[:3]).T
    torch.testing.assert_close(pixels[:, :2] / pixels[:, 2:], torch.tensor([[32.0, 32.0], [44.8, 44.8]]))


def test_quaternions_match_viser_and_round_trip():
    """viser's (w, x, y, z) is cdcgs's: cdcgs.geometry.quat_to_rotation gives viser's matrices, and
    the viewer's matrix_to_quat inverts it."""
    import viser.transforms as tf

    g = np.random.default_rng(0)
    for q in [*g.normal(size=(20, 4)), (1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 0, 1), (0, 0.6, 0.8, 0)]:
        q = np.asarray(q, float) / np.linalg.norm(q)
        rotation = quat_to_rotation(torch.from_numpy(q)).numpy()
        np.testing.assert_allclose(rotation, tf.SO3(q).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(matrix_to_quat(rotation), q if q[0] >= 0 else -q, atol=1e-12)


def test_training_camera_round_trip():
    viewmat = look_at((0.3, -1.2, -4.0), (0.1, 0.2, 0.3))
    K = torch.tensor([[80.0, 0.0, 40.0], [0.0, 80.0, 30.0], [0.0, 0.0, 1.0]])
    wxyz, position, fov = pinhole_to_viser(viewmat, K, 60)
    np.testing.assert_allclose(position, [0.3, -1.2, -4.0], atol=1e-5)
    assert fov == pytest.approx(2 * math.atan(30 / 80))
    back, K2, width, height = viser_to_pinhole(wxyz, position, fov, 80 / 60, 60)
    torch.testing.assert_close(back, viewmat, atol=1e-5, rtol=0)
    torch.testing.assert_close(K2, K)
    assert (width, height) == (80, 60)


# --------------------------------------------------------------------------------- scheduling


def test_first_frame_is_quick_then_sharpens_when_the_camera_stops():
    s = RenderScheduler(max_fps=30.0, settle_seconds=0.3, moving_height=200)
    assert s.next_frame(0.0, "pose A", "model", 480) == 200  # new camera: moving resolution
    assert s.next_frame(0.1, "pose A", "model", 480) is None  # unchanged, not settled yet
    assert s.next_frame(0.35, "pose A", "model", 480) == 480  # still for 0.3 s: full resolution
    assert s.next_frame(0.5, "pose A", "model", 480) is None  # nothing changed: no frame
    assert s.next_frame(5.0, "pose A", "model", 480) is None


def test_frames_follow_camera_changes_at_a_capped_rate():
    s = RenderScheduler(max_fps=10.0, settle_seconds=0.3, moving_height=200)
    times = [i * 0.01 for i in range(100)]  # the camera moves every 10 ms for a second
    frames = [t for t in times if s.next_frame(t, ("pose", t), "model", 480) is not None]
    assert len(frames) == 10
    assert all(b - a >= 0.1 - 1e-9 for a, b in itertools.pairwise(frames))


def test_content_change_with_a_still_camera_renders_full_resolution():
    s = RenderScheduler(max_fps=30.0, settle_seconds=0.3, moving_height=200)
    s.next_frame(0.0, "pose", "model 1", 480)
    assert s.next_frame(1.0, "pose", "model 1", 480) == 480
    assert s.next_frame(2.0, "pose", "model 2", 480) == 480  # a new snapshot, mode or cap
    assert s.next_frame(3.0, "pose", "model 2", 480) is None


def test_moving_resolution_adapts_to_the_frame_time():
    s = RenderScheduler(frame_budget_seconds=0.1, min_height=90, moving_height=400)
    s.rendered(400, 0.4, 1000)  # 4x over budget: sqrt(1/4) = half the height
    assert s.moving_height == 200
    s.rendered(200, 10.0, 1000)  # far over: at most halved per frame, never below the floor
    assert s.moving_height == 100
    s.rendered(100, 0.001, 1000)
    assert s.moving_height == 150  # far under: at most x1.5 per frame
    for _ in range(20):
        s.rendered(s.moving_height, 0.001, 1000)
    assert s.moving_height == 1000  # never above the full height
    assert s.next_frame(0.0, "pose", "model", 480) == 480


def test_render_share_bounds_the_time_spent_rendering():
    """Beside a training: a burst of frames after a pause, then at most render_share of the time."""
    s = RenderScheduler(max_fps=10.0, render_share=0.05, burst_seconds=1.0, frame_budget_seconds=1.0, moving_height=200)
    now, busy, frames = 0.0, 0.0, 0
    while now < 100.0:  # the camera moves all the time; each frame takes 0.2 s
        if s.next_frame(now, ("pose", now), "model", 200) is not None:
            s.rendered(200, 0.2, 200)
            frames, busy = frames + 1, busy + 0.2
        now += 0.01
    assert frames >= 5 and busy <= 0.05 * 100.0 + 1.0 + 0.2  # the share, the burst, one frame over
    first_second = RenderScheduler(
        max_fps=10.0, render_share=0.05, burst_seconds=1.0, frame_budget_seconds=1.0, moving_height=200
    )
    count = 0
    for i in range(100):
        if first_second.next_frame(i * 0.01, ("pose", i), "model", 200) is not None:
            first_second.rendered(200, 0.2, 200)
            count += 1
    # The burst: 1 s of credit (and the 0.025 s accrued meanwhile) pays for five 0.2 s frames, and
    # a frame starts while any credit is left, so a sixth; then none until the debt is paid.
    assert count == 6


def test_snapshots_are_due_only_while_watched_and_old():
    live = LiveModel(snapshot=None, refresh_seconds=1.0)
    assert not live.due(100.0, watched=False)
    assert live.due(100.0, watched=True)
    live.replace("snapshot", 100.0)
    assert live.version == 1 and live.snapshot == "snapshot"
    assert not live.due(100.5, watched=True)
    assert live.due(101.0, watched=True)
    assert not live.due(101.0, watched=False)
    # Slow frames (0.4 s on a CPU) make snapshots rarer: re-renders take at most 5% of the time.
    live = LiveModel(snapshot=None, refresh_seconds=1.0, render_share=0.05)
    live.replace("snapshot", 100.0)
    assert not live.due(107.9, watched=True, frame_seconds=0.4)
    assert live.due(108.0, watched=True, frame_seconds=0.4)
    assert live.due(101.0, watched=True, frame_seconds=0.01)  # fast frames: refresh_seconds rules


# --------------------------------------------------------------------------------- rendering


def small_model(device, n=120, seed=0):
    scene = make_scene(n=n, sh_degree=1, seed=seed, hard_cases=False)
    params = {
        "means": scene.means,
        "log_scales": scene.scales.log(),
        "quats": scene.quats,
        "opacity_logits": torch.logit(scene.opacities.clamp(1e-4, 1 - 1e-4)),
        "sh_dc": scene.sh[:, :1],
        "sh_rest": scene.sh[:, 1:],
    }
    return GaussianModel({k: v.to(device) for k, v in params.items()}, max_sh_degree=1, sh_degree=1), scene


def test_snapshot_is_a_detached_copy(device):
    model, _ = small_model(device)
    snapshot = Snapshot.of(model, step=7)
    assert snapshot.num == 120 and snapshot.step == 7 and snapshot.sh_degree == 1
    assert not any(t.requires_grad for t in (snapshot.means, snapshot.scales, snapshot.sh))
    with torch.no_grad():
        model.params["means"] += 1.0
    assert not torch.equal(snapshot.means, model.params["means"])


def test_offer_takes_a_snapshot_only_when_watched_and_due(device):
    model, _ = small_model(device)
    viewer = Viewer(
        Viewable(Snapshot.of(model, 0), "test", [], Complexity()), ViewerSettings(refresh_seconds=60.0), live=True
    )
    viewer.offer(model, 1)
    assert viewer.model.version == 0, "nobody watches: no snapshot"
    viewer.renderer.watched = True
    viewer.offer(model, 2)
    assert viewer.model.version == 1 and viewer.model.snapshot.step == 2
    viewer.offer(model, 3)
    assert viewer.model.version == 1, "the snapshot is younger than refresh_seconds"


def test_frames_of_each_mode(device):
    model, scene = small_model(device)
    viewer = Viewer(Viewable(Snapshot.of(model), "test", [], Complexity(unavailable="a PLY file")))
    wxyz, position, fov = pinhole_to_viser(scene.viewmat, scene.K, scene.height)
    frames = {}
    for mode in ("colour", "depth", "alpha", "complexity"):
        viewer.renderer.mode = mode
        frames[mode] = viewer.renderer.render(wxyz, position, fov, 1.5, 48)
        assert frames[mode].shape == (48, 72, 3) and frames[mode].dtype == np.uint8
    # The colour frame is what rasterize renders from the same camera.
    viewmat, K, width, height = viser_to_pinhole(wxyz, position, fov, 1.5, 48)
    with torch.no_grad():
        image, alpha, _ = rasterize(
            **model.render_args(), viewmat=viewmat, K=K, width=width, height=height, render_depth=True
        )
    expected = (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
    np.testing.assert_array_equal(frames["colour"], expected)
    np.testing.assert_array_equal(
        frames["alpha"][..., 0], (alpha.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
    )
    assert frames["colour"].std() > 5 and frames["depth"].std() > 5
    assert not np.array_equal(frames["depth"], frames["colour"])
    # No training images: the complexity mode says so (in the page) and shows colour.
    np.testing.assert_array_equal(frames["complexity"], frames["colour"])
    assert "not available" in mode_text("complexity", viewer.viewable.complexity)


# ----------------------------------------------------------------------- loading, output folders


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A finished cdcgs run on a small procedural scene (a few iterations, no densification)."""
    root = tmp_path_factory.mktemp("viewer_run")
    scene = make_procedural_scene(root / "scene", views=8, width=48, height=36, points=400)
    config = TrainConfig(
        data=DataConfig(data=scene),
        out=str(root / "run"),
        iters=20,
        device=DEFAULT_DEVICE,
        eval_every=0,
        checkpoint_every=0,
        progress=False,
        save_renders=False,
    )
    Trainer(config, {"densify_from": 10**6}).run()
    return root / "run"


def gamma_by_hand(viewable, method: str, view_aggregation: str) -> torch.Tensor:
    """Γ of CDC-GS written out: per view the max over its pixels of HF w / w_max, then the max over
    the views, or the mean over the views that see the Gaussian (their images are loaded)."""
    snapshot = viewable.snapshot
    per_view, seen = [], []
    with torch.no_grad():
        for view in viewable.views:
            _, _, info = rasterize(
                **snapshot.render_args(), viewmat=view.viewmat, K=view.K, width=view.width, height=view.height
            )
            max_out, _, count = gaussian_complexity(info, complexity_map(view.image, method))
            per_view.append(max_out)
            seen.append(count > 0)
    per_view, seen = torch.stack(per_view), torch.stack(seen)
    if view_aggregation == "max":
        return per_view.max(dim=0).values
    return per_view.sum(dim=0) / seen.sum(dim=0).clamp_min(1)


def test_output_folder_brings_cameras_and_complexity(tiny_run):
    viewable = load_viewable(tiny_run, DEFAULT_DEVICE)
    assert viewable.snapshot.num == 400 and len(viewable.views) == 7  # 8 views, every 8th held out
    assert viewable.complexity.unavailable is None and not viewable.notes
    assert viewable.complexity.view_aggregation == "max"  # the run's strategy recorded none: CDC-GS's
    gamma = viewable.complexity.compute(viewable.snapshot)
    assert gamma.shape == (400,) and gamma.min() >= 0.0 and gamma.max() <= 1.0 and gamma.max() > 0.1
    torch.testing.assert_close(gamma, gamma_by_hand(viewable, "dwt", "max"))
    viewer = Viewer(viewable)
    viewer.renderer.mode = "complexity"
    wxyz, position, fov = pinhole_to_viser(viewable.views[0].viewmat, viewable.views[0].K, 36)
    complexity = viewer.renderer.render(wxyz, position, fov, 48 / 36, 36)
    viewer.renderer.mode = "colour"
    assert not np.array_equal(complexity, viewer.renderer.render(wxyz, position, fov, 48 / 36, 36))


def test_complexity_is_measured_as_the_run_recorded(tiny_run, tmp_path):
    """A run whose strategy measured Γ with another method and as the mean over the views shows that
    Γ, not the default max over the views."""
    recorded = tmp_path / "run"
    shutil.copytree(tiny_run, recorded)
    config = read_json(recorded / "config.json")
    strategy = {"complexity_method": "sobel", "pixel_aggregation": "max", "view_aggregation": "mean"}
    config["strategy"] = {**config.get("strategy", {}), **strategy}
    write_json(recorded / "config.json", config)
    viewable = load_viewable(recorded, DEFAULT_DEVICE)
    complexity = viewable.complexity
    assert (complexity.method, complexity.pixel_aggregation, complexity.view_aggregation) == ("sobel", "max", "mean")
    gamma = complexity.compute(viewable.snapshot)
    mean = gamma_by_hand(viewable, "sobel", "mean")
    torch.testing.assert_close(gamma, mean)
    assert (gamma < gamma_by_hand(viewable, "sobel", "max") - 1e-3).any(), "the mean differs from the max somewhere"
    assert "mean over 7 training views" in mode_text("complexity", complexity)


def test_output_folder_whose_scene_moved_still_opens(tiny_run, tmp_path):
    moved = tmp_path / "run"
    shutil.copytree(tiny_run, moved)
    config = read_json(moved / "config.json")
    config["train"]["data"]["data"] = str(tmp_path / "gone")
    write_json(moved / "config.json", config)
    viewable = load_viewable(moved, DEFAULT_DEVICE)
    assert viewable.snapshot.num == 400 and viewable.views == []
    assert "gone" in viewable.notes[0] and "could not be loaded" in viewable.complexity.unavailable


def test_ply_from_another_tool_opens(tmp_path, device):
    model, _ = small_model(device)
    write_ply(tmp_path / "scene.ply", model.to_ply())
    viewable = load_viewable(tmp_path / "scene.ply", device)
    assert viewable.snapshot.num == 120 and viewable.snapshot.sh_degree == 1 and viewable.views == []
    assert "PLY" in viewable.complexity.unavailable


def bad_inputs(tmp_path, tiny_run):
    (tmp_path / "notes.ply").write_text("hello\n")
    n = 10
    write_ply(
        tmp_path / "whole.ply",
        GaussianPly(torch.zeros(n, 3), torch.zeros(n, 3), torch.ones(n, 4), torch.zeros(n), torch.zeros(n, 1, 3)),
    )
    data = (tmp_path / "whole.ply").read_bytes()
    (tmp_path / "truncated.ply").write_bytes(data[:-20])
    write_ply(
        tmp_path / "empty.ply",
        GaussianPly(torch.zeros(0, 3), torch.zeros(0, 3), torch.ones(0, 4), torch.zeros(0), torch.zeros(0, 1, 3)),
    )
    marked_means = torch.zeros(n, 3)
    marked_means[4, 1] = 12345.0  # write_ply refuses NaN: the file gets it by its bytes
    write_ply(
        tmp_path / "nan.ply",
        GaussianPly(marked_means, torch.zeros(n, 3), torch.ones(n, 4), torch.zeros(n), torch.zeros(n, 1, 3)),
    )
    data = (tmp_path / "nan.ply").read_bytes()
    (tmp_path / "nan.ply").write_bytes(data.replace(np.float32(12345.0).tobytes(), np.float32("nan").tobytes()))
    (tmp_path / "folder").mkdir()
    (tmp_path / "unfinished").mkdir()
    shutil.copy(tiny_run / "config.json", tmp_path / "unfinished")
    return {
        "missing.ply": "no such file or folder",
        "notes.ply": "not a PLY file",
        "truncated.ply": "the body is truncated",
        "empty.ply": "holds no Gaussians",
        "nan.ply": "NaN or infinite values",
        "folder": "not a cdcgs output folder",
        "unfinished": "holds no model yet",
    }


def test_bad_paths_raise_input_errors_naming_them(tmp_path, tiny_run):
    for name, problem in bad_inputs(tmp_path, tiny_run).items():
        with pytest.raises(InputError, match=problem) as err:
            load_viewable(tmp_path / name, "cpu")
        assert err.value.path.endswith(name)


def test_cdcgs_view_reports_bad_input_in_the_terminal(tmp_path, tiny_run, capsys):
    for name, problem in bad_inputs(tmp_path, tiny_run).items():
        assert cli_main(["view", str(tmp_path / name), "--port", "0"]) == 2
        message = capsys.readouterr().err
        assert (
            message.startswith("cdcgs view: ") and name in message and problem in message and "Traceback" not in message
        )
    ply = str(tmp_path / "whole.ply")
    refused = (
        (["--max-fps", "0"], "max_fps must be positive"),
        (["--port", "70000"], "port must be an int in 0..65535"),
        (["--max-height", "4"], "max_height must be at least 16"),
        (["--device", "tpu"], "device 'tpu'"),
        (["--host", "no.such.host.invalid"], "is not an address of this machine"),
    )
    for options, problem in refused:
        assert cli_main(["view", ply, *options]) == 2
        assert problem in capsys.readouterr().err
    assert cli_main(["view", ply, "--port", "eighty"]) == 2  # argparse: usage and exit status 2
    assert "invalid int value" in capsys.readouterr().err


def test_port_in_use_is_refused_by_name(tmp_path, tiny_run, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert cli_main(["view", str(tiny_run), "--port", str(port)]) == 2
        message = capsys.readouterr().err
        assert f"cannot listen on 127.0.0.1:{port}" in message and "choose another port" in message


class WatchedTrainingViewer(TrainingViewer):
    """A TrainingViewer as if a browser were connected all along."""

    def on_start(self, trainer):
        super().on_start(trainer)
        self.viewer.renderer.watched = True


def test_training_hands_snapshots_to_its_viewer(tiny_run, tmp_path, monkeypatch):
    """`cdcgs train --view`: the callback starts the viewer on its port, hands it snapshots while
    watched, and stops it with the training."""
    monkeypatch.setattr(RenderLoop, "_run", lambda self, server, on_tick: None)  # nothing to reset the watch flag
    config = read_json(tiny_run / "config.json")["train"]
    run = TrainConfig(
        data=DataConfig(data=config["data"]["data"]),
        out=str(tmp_path / "live"),
        iters=5,
        device=DEFAULT_DEVICE,
        eval_every=0,
        checkpoint_every=0,
        progress=False,
        save_renders=False,
    )
    callback = WatchedTrainingViewer(ViewerSettings(port=0, max_fps=10.0, refresh_seconds=0.0))
    Trainer(run, {"densify_from": 10**6}, callbacks=[callback]).run()
    viewer = callback.viewer
    assert (
        viewer.settings.port == 0 and viewer.settings.host == "127.0.0.1" and viewer.url.startswith("http://127.0.0.1:")
    )
    assert viewer.live and viewer.model.version == 5 and viewer.model.snapshot.step == 5
    assert len(viewer.viewable.views) == 7 and viewer.viewable.complexity.unavailable is None
    assert viewer._server is None, "the viewer stops with the training"


def test_training_viewer_measures_complexity_as_the_strategy_does(tiny_run, monkeypatch, capsys):
    """The callback's viewer takes the trainer's views, background and Γ options (Strategy.config())."""
    monkeypatch.setattr(RenderLoop, "_run", lambda self, server, on_tick: None)
    run = load_viewable(tiny_run, DEFAULT_DEVICE)
    model, _ = small_model(DEFAULT_DEVICE)
    strategy = {"complexity_method": "sobel", "pixel_aggregation": "mean", "view_aggregation": "mean"}
    config = TrainConfig(data=DataConfig(data="unused"), out="outputs/some run/", background="white")
    trainer = types.SimpleNamespace(
        config=config,
        scene=types.SimpleNamespace(train=run.views),
        model=model,
        step=3,
        strategy=types.SimpleNamespace(config=lambda: strategy),
        device=torch.device(DEFAULT_DEVICE),
    )
    callback = TrainingViewer(ViewerSettings(port=0, refresh_seconds=0.0))
    try:
        callback.on_start(trainer)
        viewer = callback.viewer
        assert "watch the training at http://127.0.0.1:" in capsys.readouterr().out
        viewable = viewer.viewable
        assert viewable.title == "some run" and viewable.background == (1.0, 1.0, 1.0) and viewable.snapshot.step == 3
        complexity = viewable.complexity
        assert (complexity.method, complexity.pixel_aggregation, complexity.view_aggregation) == (
            "sobel",
            "mean",
            "mean",
        )
        callback.on_step(trainer)
        assert viewer.model.version == 0, "nobody watches: no snapshot"
        viewer.renderer.watched = True
        trainer.step = 4
        callback.on_step(trainer)
        assert viewer.model.version == 1 and viewer.model.snapshot.step == 4
    finally:
        callback.on_end(trainer)
    assert callback.viewer._server is None
