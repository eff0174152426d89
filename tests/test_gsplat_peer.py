"""benchmarks/peers/gsplat_train.py without gsplat and without a GPU: its refusals, its schedules,
and its loop end to end on the CPU with a stand-in for gsplat's rasterization and strategy."""

import dataclasses
import importlib.util
import json
import math
import os
import subprocess
import sys
import types

import pytest
import torch
from conftest import test_devices

from cdcgs.datasets.procedural import make_procedural_scene
from cdcgs.io import load_scene, scene_extent
from cdcgs.train.config import LearningRates
from cdcgs.train.model import GaussianModel
from cdcgs.train.trainer import Trainer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "benchmarks", "peers", "gsplat_train.py")
spec = importlib.util.spec_from_file_location("gsplat_train", SCRIPT)
peer = importlib.util.module_from_spec(spec)
sys.modules["gsplat_train"] = peer  # its dataclasses look their module up there
spec.loader.exec_module(peer)


def fake_gsplat_module() -> types.ModuleType:
    module = types.ModuleType("gsplat")
    module.__version__ = "1.5.3"
    module.rasterization = fake_rasterization
    module.DefaultStrategy = RecordingStrategy
    module.MCMCStrategy = RecordingMCMCStrategy
    return module


def stand_in_api(rasterization=None) -> types.SimpleNamespace:
    return types.SimpleNamespace(
        rasterization=rasterization or fake_rasterization,
        DefaultStrategy=RecordingStrategy,
        MCMCStrategy=RecordingMCMCStrategy,
        version="1.5.3",
    )


def test_refuses_without_gsplat(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # import gsplat -> ImportError
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert peer.main(["--data", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "gsplat is not importable" in err and "CUDA" not in err
    assert not (tmp_path / "out").exists()


def test_refuses_without_cuda(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "gsplat", fake_gsplat_module())
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert peer.main(["--data", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "no CUDA device" in err and "not importable" not in err
    assert not (tmp_path / "out").exists()


def test_command_line_refuses_on_a_machine_without_gsplat_or_cuda(tmp_path):
    if importlib.util.find_spec("gsplat") is not None and torch.cuda.is_available():
        pytest.skip("gsplat and a CUDA GPU are both here: the command would train")
    command = [sys.executable, SCRIPT, "--data", str(tmp_path), "--out", str(tmp_path / "out")]
    run = subprocess.run(command, check=False, capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    assert "cannot run the gsplat peer here" in run.stderr and "Traceback" not in run.stderr


def test_refuses_a_missing_scene_and_an_existing_run(tmp_path, capsys):
    assert peer.main(["--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")]) == 2
    assert "no such scene folder" in capsys.readouterr().err
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "metrics.json").write_text("{}")
    assert peer.main(["--data", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "already holds a run" in capsys.readouterr().err


def test_means_learning_rate_decays_to_a_hundredth():
    scale = 5.16
    assert peer.means_lr(0, 30_000, scale) == pytest.approx(1.6e-4 * scale, rel=1e-12)
    assert peer.means_lr(30_000, 30_000, scale) == pytest.approx(1.6e-6 * scale, rel=1e-12)
    # the rate the last step uses (0-based step 29,999): ExponentialLR has decayed it 29,999 times
    assert peer.means_lr(29_999, 30_000, scale) == pytest.approx(1.6e-6 * scale, rel=2e-4)
    gamma = 0.01 ** (1 / 30_000)
    assert peer.means_lr(1234, 30_000, scale) == pytest.approx(1.6e-4 * scale * gamma**1234, rel=1e-9)


def test_rates_are_gsplats_and_equal_ours():
    # Our default is the strategy's, 0.025 as the CDC-GS code; the pair runs ours with gsplat's 0.05.
    assert LearningRates().opacity_logits is None
    ours = LearningRates(opacity_logits=0.05)
    gsplat = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3, "shN": 2.5e-3 / 20}
    assert gsplat == peer.GSPLAT_LRS
    ours_in_order = [ours.means_init, ours.log_scales, ours.quats, ours.opacity_logits, ours.sh_dc, ours.sh_rest]
    assert ours_in_order == list(gsplat.values())
    assert pytest.approx(ours.means_final / ours.means_init) == peer.MEANS_LR_END


def test_cap_max_is_mcmcs_and_positive(tmp_path, capsys):
    base = ["--data", str(tmp_path), "--out", str(tmp_path / "out")]
    assert peer.parse_args(base).strategy == "default" and peer.parse_args(base).cap_max is None
    assert peer.parse_args([*base, "--strategy", "mcmc"]).cap_max == 1_000_000  # MCMCStrategy's default
    assert peer.parse_args([*base, "--strategy", "mcmc", "--cap-max", "901363"]).cap_max == 901_363
    refused = {
        ("--strategy", "mcmc", "--cap-max", "0"): "--cap-max must be positive, got 0",
        ("--strategy", "mcmc", "--cap-max", "-5"): "--cap-max must be positive, got -5",
        ("--cap-max", "901363"): "--cap-max is MCMCStrategy's cap_max: it needs --strategy mcmc",
        ("--strategy", "default", "--cap-max", "901363"): "it needs --strategy mcmc (got --strategy default)",
        ("--strategy", "mcmc-cdc"): "argument --strategy: invalid choice: 'mcmc-cdc'",
    }
    for extra, message in refused.items():
        with pytest.raises(SystemExit) as exit_info:
            peer.parse_args([*base, *extra])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err, extra


def test_regularization_by_hand():
    opacities = torch.tensor([-2.0, 0.0, 3.0], requires_grad=True)
    scales = torch.tensor([[0.1, 0.2, 0.3], [1.0, 2.0, 0.5], [0.01, 0.02, 0.04]]).log().requires_grad_()
    params = {"opacities": opacities, "scales": scales}
    assert peer.regularization(params, peer.SETTINGS["default"]) is None
    value = peer.regularization(params, peer.SETTINGS["mcmc"])
    sigmoids = [1 / (1 + math.exp(2.0)), 0.5, 1 / (1 + math.exp(-3.0))]
    sizes = [0.1, 0.2, 0.3, 1.0, 2.0, 0.5, 0.01, 0.02, 0.04]
    assert value.item() == pytest.approx(0.01 * sum(sigmoids) / 3 + 0.01 * sum(sizes) / 9, rel=1e-6)
    value.backward()  # d/dx sigmoid = s (1 - s); d/dx exp = exp
    torch.testing.assert_close(opacities.grad, torch.tensor([0.01 * o * (1 - o) / 3 for o in sigmoids]))
    torch.testing.assert_close(scales.grad, torch.tensor(sizes).reshape(3, 3) * 0.01 / 9)


def test_sh_degree_schedule():
    assert [peer.sh_degree_at(s) for s in (0, 999, 1000, 1999, 2000, 3000, 29_999)] == [0, 0, 1, 1, 2, 3, 3]


def test_view_order_is_our_trainers():
    trainer = Trainer.__new__(Trainer)  # only what _next_view reads
    trainer.view_queue, trainer.scene = [], types.SimpleNamespace(train=[None] * 11)
    trainer.view_generator = torch.Generator().manual_seed(7 + 1)
    order = peer.view_order(11, seed=7)
    assert [next(order) for _ in range(40)] == [trainer._next_view() for _ in range(40)]


# ---------------------------------------------------------------------------------------------
# A stand-in for gsplat: a dense, differentiable splatter with gsplat's signature and info keys,
# and a strategy with DefaultStrategy's hooks that records how it is called.

RENDERS: list = []  # the SH degree of each render
CALLS: list = []  # the strategy hooks' calls, in order
START: dict = {}  # the parameters and rates check_sanity saw
GRADIENTS: list = []  # with HOOK_GRADIENTS: each step's parameters and the opacity and scale gradients
HOOK_GRADIENTS = {"on": False}


def fake_rasterization(
    *,
    means,
    quats,
    scales,
    opacities,
    colors,
    viewmats,
    Ks,
    width,
    height,
    near_plane,
    far_plane,
    sh_degree,
    packed,
    absgrad,
    rasterize_mode,
    backgrounds,
):
    assert packed is False and absgrad is False and rasterize_mode == "classic"
    assert backgrounds is None or (backgrounds.shape == (1, 3) and not backgrounds.any())  # black: none in training
    assert viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3) and colors.shape[1:] == (16, 3) and 0 <= sh_degree <= 3
    RENDERS.append(sh_degree)
    cam = means @ viewmats[0, :3, :3].T + viewmats[0, :3, 3]
    front = cam[:, 2] > near_plane
    z = cam[:, 2].clamp_min(near_plane)
    u, v = Ks[0, 0, 0] * cam[:, 0] / z + Ks[0, 0, 2], Ks[0, 1, 1] * cam[:, 1] / z + Ks[0, 1, 2]
    means2d = torch.stack([u, v], -1)[None]  # [1, N, 2], a node of the graph as gsplat's
    sigma = (scales.max(-1).values * Ks[0, 0, 0] / z).clamp_min(0.5)
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    pixels = torch.stack([xs, ys], -1).reshape(-1, 2).to(means)
    falloff = torch.exp(-0.5 * ((pixels[None] - means2d[0][:, None]) ** 2).sum(-1) / sigma[:, None] ** 2)
    weight = opacities[:, None] * falloff * front[:, None]  # [N, pixels]
    alpha = 1 - torch.exp(-weight.sum(0))
    rgb = (0.28209479177387814 * colors[:, 0] + 0.5).clamp_min(0)
    image = (weight.T @ rgb) / (weight.sum(0)[:, None] + 1e-6) * alpha[:, None]
    radii = ((3 * sigma).ceil().int() * front)[None, :, None].expand(1, -1, 2)
    info = {"means2d": means2d, "radii": radii, "width": width, "height": height, "n_cameras": 1, "gaussian_ids": None}
    return image.reshape(1, height, width, 3), alpha.reshape(1, height, width, 1), info


def record_start(params, optimizers):
    assert set(params) == set(optimizers) == {"means", "scales", "quats", "opacities", "sh0", "shN"}
    for name, optimizer in optimizers.items():
        (group,) = optimizer.param_groups
        assert group["params"] == [params[name]] and group["eps"] == 1e-15 and group["betas"] == (0.9, 0.999)
    START.update({name: p.detach().clone() for name, p in params.items()})
    START.update({f"lr {name}": o.param_groups[0]["lr"] for name, o in optimizers.items()})


@dataclasses.dataclass
class RecordingStrategy:
    absgrad: bool = False
    refine_every: int = 100

    def check_sanity(self, params, optimizers):
        record_start(params, optimizers)

    def initialize_state(self, scene_scale: float = 1.0):
        return {"scene_scale": scene_scale}

    def step_pre_backward(self, params, optimizers, state, step, info):
        info["means2d"].retain_grad()
        CALLS.append(("pre", step))

    def step_post_backward(self, params, optimizers, state, step, info, packed=False):
        assert packed is False and info["means2d"].grad is not None
        assert params["means"].grad is None  # called after the optimizer step, as simple_trainer
        CALLS.append(("post", step, optimizers["means"].param_groups[0]["lr"]))


@dataclasses.dataclass
class RecordingMCMCStrategy:
    """MCMCStrategy's fields and defaults and its hooks' signatures (gsplat 1.5.3): no absgrad, a
    state without the scene scale, the base class's step_pre_backward, step_post_backward with lr."""

    cap_max: int = 1_000_000
    noise_lr: float = 5e5
    refine_start_iter: int = 500
    refine_stop_iter: int = 25_000
    refine_every: int = 100
    min_opacity: float = 0.005
    verbose: bool = False

    def check_sanity(self, params, optimizers):
        record_start(params, optimizers)

    def initialize_state(self):
        return {"binoms": torch.zeros(51, 51)}

    def step_pre_backward(self, *args, **kwargs):
        CALLS.append(("pre", kwargs["step"]))
        if HOOK_GRADIENTS["on"]:
            record = {name: params.detach().clone() for name, params in kwargs["params"].items()}
            GRADIENTS.append(record)
            for name in ("opacities", "scales"):
                kwargs["state"][name] = kwargs["params"][name].register_hook(
                    lambda grad, name=name: record.update({f"grad {name}": grad.clone()})
                )

    def step_post_backward(self, params, optimizers, state, step, info, lr):
        assert params["means"].grad is None  # called after the optimizer step, as simple_trainer
        for name in ("opacities", "scales"):
            if name in state:
                state.pop(name).remove()
        CALLS.append(("post", step, lr, optimizers["means"].param_groups[0]["lr"]))


@pytest.mark.skipif("cpu" not in test_devices(), reason="CDCGS_TEST_DEVICES leaves out the CPU (no Warp CPU compiler)")
def test_training_loop_end_to_end_on_the_cpu_with_a_stand_in(tmp_path, monkeypatch):
    scene = make_procedural_scene(tmp_path / "scene", views=8, width=48, height=36, points=300)
    out = tmp_path / "out"
    out.mkdir()
    args = peer.parse_args(["--data", scene, "--out", str(out), "--iters", "12", "--no-progress", "--seed", "3"])
    RENDERS.clear(), CALLS.clear(), START.clear()
    assert peer.train(args, stand_in_api(), torch.device("cpu")) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    scale = metrics["protocol"]["scene_scale"]
    assert [c[:2] for c in CALLS] == [(kind, s) for s in range(12) for kind in ("pre", "post")]
    assert [c[2] for c in CALLS[1::2]] == pytest.approx([peer.means_lr(s, 12, scale) for s in range(12)])
    assert len(RENDERS) == 12 + 2 * metrics["test"]["views"]  # evaluate() renders each test view twice
    assert metrics["iterations"] == 12 and metrics["train_seconds"] > 0 and metrics["device"] == "cpu"
    assert metrics["strategy"]["name"] == "gsplat 1.5.3 DefaultStrategy" and metrics["test"]["views"] == 1
    assert 0 < metrics["test"]["ssim"] <= 1 and metrics["test"]["psnr"] > 0 and (out / "point_cloud.ply").is_file()
    assert metrics["protocol"]["train_views"] == 7 and metrics["protocol"]["adam"] == "torch default"  # CPU: unfused
    assert [metrics["protocol"][k] for k in ("init_opacity", "init_scale", "opacity_reg", "scale_reg")] == [
        0.1,
        1,
        0,
        0,
    ]
    # our trainer's initial Gaussians, gsplat's rates, gsplat's scene_scale (all cameras)
    loaded = load_scene(scene, images="images", progress=False)
    ours = GaussianModel.from_points(loaded.points, loaded.colors, max_sh_degree=3, init_opacity=0.1)
    for name, ours_name in peer.FROM_OURS.items():
        torch.testing.assert_close(START[name], ours.params[ours_name].detach(), rtol=0, atol=0)
    assert scale == pytest.approx(scene_extent(loaded.views))
    assert {name: START[f"lr {name}"] for name in peer.GSPLAT_LRS} == pytest.approx(
        {**peer.GSPLAT_LRS, "means": 1.6e-4 * scale}
    )
    # what benchmarks/run.py's training section reads
    monkeypatch.syspath_prepend(os.path.join(ROOT, "benchmarks"))
    import run as suite

    rows = []
    suite.section_training(types.SimpleNamespace(training_run=[str(out)], peer_training=None), rows.append)
    assert rows[0]["strategy"] == "gsplat 1.5.3 DefaultStrategy" and rows[0]["iterations"] == 12
    assert rows[0]["psnr"] == metrics["test"]["psnr"] and rows[0]["peak_gpu_memory_gb"] is None


@pytest.mark.skipif("cpu" not in test_devices(), reason="CDCGS_TEST_DEVICES leaves out the CPU (no Warp CPU compiler)")
def test_mcmc_end_to_end_on_the_cpu_with_a_stand_in(tmp_path):
    scene = make_procedural_scene(tmp_path / "scene", views=8, width=48, height=36, points=300)
    out = tmp_path / "out"
    out.mkdir()
    options = ["--iters", "12", "--no-progress", "--seed", "3", "--strategy", "mcmc", "--cap-max", "5000"]
    args = peer.parse_args(["--data", scene, "--out", str(out), *options])
    RENDERS.clear(), CALLS.clear(), START.clear()
    assert peer.train(args, stand_in_api(), torch.device("cpu")) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    scale = metrics["protocol"]["scene_scale"]
    assert [c[:2] for c in CALLS] == [(kind, s) for s in range(12) for kind in ("pre", "post")]
    # the optimizer stepped with this step's rate; the noise gets the next one, as simple_trainer's
    # scheduler gives it after its step
    assert [c[3] for c in CALLS[1::2]] == pytest.approx([peer.means_lr(s, 12, scale) for s in range(12)])
    assert [c[2] for c in CALLS[1::2]] == pytest.approx([peer.means_lr(s + 1, 12, scale) for s in range(12)])
    assert metrics["strategy"] == {
        "name": "gsplat 1.5.3 MCMCStrategy",
        "cap_max": 5000,
        "noise_lr": 5e5,
        "refine_start_iter": 500,
        "refine_stop_iter": 25_000,
        "refine_every": 100,
        "min_opacity": 0.005,
        "verbose": False,
    }
    settings = [metrics["protocol"][k] for k in ("init_opacity", "init_scale", "opacity_reg", "scale_reg")]
    assert settings == [0.5, 0.1, 0.01, 0.01] and metrics["test"]["views"] == 1
    # simple_trainer's mcmc start (opacity 0.5, scales x 0.1), which is our mcmc preset's
    loaded = load_scene(scene, images="images", progress=False)
    plain = GaussianModel.from_points(loaded.points, loaded.colors, max_sh_degree=3, init_opacity=0.1)
    ours = GaussianModel.from_points(loaded.points, loaded.colors, max_sh_degree=3, init_opacity=0.5, scale_factor=0.1)
    for name, ours_name in peer.FROM_OURS.items():
        torch.testing.assert_close(START[name], ours.params[ours_name].detach(), rtol=0, atol=0)
    torch.testing.assert_close(torch.sigmoid(START["opacities"]), torch.full((300,), 0.5), rtol=0, atol=0)
    torch.testing.assert_close(START["scales"], plain.params["log_scales"] + math.log(0.1))


@pytest.mark.skipif("cpu" not in test_devices(), reason="CDCGS_TEST_DEVICES leaves out the CPU (no Warp CPU compiler)")
def test_mcmc_regularisers_reach_the_opacity_and_scale_gradients(tmp_path):
    def render_without_opacities_or_scales(**arguments):  # the loss's gradient there: the regularisers'
        return fake_rasterization(
            **{**arguments, "opacities": arguments["opacities"].detach(), "scales": arguments["scales"].detach()}
        )

    scene = make_procedural_scene(tmp_path / "scene", views=8, width=48, height=36, points=300)
    out = tmp_path / "out"
    out.mkdir()
    args = peer.parse_args(["--data", scene, "--out", str(out), "--iters", "3", "--no-progress", "--strategy", "mcmc"])
    CALLS.clear(), GRADIENTS.clear()
    HOOK_GRADIENTS["on"] = True
    try:
        assert peer.train(args, stand_in_api(render_without_opacities_or_scales), torch.device("cpu")) == 0
    finally:
        HOOK_GRADIENTS["on"] = False
    assert len(GRADIENTS) == 3
    for record in GRADIENTS:  # 0.01 mean(sigmoid(o)) + 0.01 mean(exp(s)), differentiated by hand
        opacity = torch.sigmoid(record["opacities"])
        torch.testing.assert_close(record["grad opacities"], 0.01 * opacity * (1 - opacity) / 300)
        torch.testing.assert_close(record["grad scales"], 0.01 * record["scales"].exp() / 900)
