"""Helpers shared by the training and strategy tests: hand-built models with known Adam moments,
fake render records, step contexts, small training configurations."""

import functools
import math
import os
import signal
from types import SimpleNamespace

import torch
from conftest import test_devices

from cdcgs.render import RasterizeInfo
from cdcgs.train.config import DataConfig, LearningRates, TrainConfig
from cdcgs.train.model import GaussianModel
from cdcgs.train.ops import make_optimizer
from cdcgs.train.strategy import StepContext
from cdcgs.train.trainer import Trainer

DEFAULT_DEVICE = (test_devices() or ["cpu"])[0]  # cpu, unless CDCGS_TEST_DEVICES narrows it
SHORT = {"densify_from": 20, "densify_until": 120, "densify_every": 20, "reset_every": 100_000}


def hand_model(n=6):
    """Gaussians at x = 0..n-1 with chosen scales and opacities, and Adam moments set to known values."""
    means = torch.zeros(n, 3)
    means[:, 0] = torch.arange(n, dtype=torch.float32)
    log_scales = torch.full((n, 3), math.log(0.005))
    log_scales[3:, 0] = math.log(0.5)  # Gaussians 3.. are large
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    opacity = torch.full((n,), 0.5)
    opacity[5] = 0.001  # Gaussian 5 is nearly transparent
    params = {
        "means": means,
        "log_scales": log_scales,
        "quats": quats,
        "opacity_logits": torch.log(opacity / (1 - opacity)),
        "sh_dc": torch.rand(n, 1, 3),
        "sh_rest": torch.zeros(n, 15, 3),
    }
    model = GaussianModel(params)
    optimizer = make_optimizer(model, LearningRates(), extent=1.0)
    for group in optimizer.param_groups:
        p = group["params"][0]
        index = torch.arange(n, dtype=torch.float32).view(-1, *[1] * (p.dim() - 1))
        value = (index + 1).expand_as(p).clone()
        optimizer.state[p] = {"step": torch.tensor(1.0), "exp_avg": value, "exp_avg_sq": value.clone()}
    return model, optimizer


def moments(optimizer, name):
    group = next(g for g in optimizer.param_groups if g["name"] == name)
    return optimizer.state[group["params"][0]]


def fake_info(grad_pixels: torch.Tensor, visible: torch.Tensor, radius: torch.Tensor, width=200, height=100):
    """What a strategy reads of a RasterizeInfo, with a chosen screen-space gradient [N, 2] in pixels."""
    assert (radius[visible] >= 1).all(), "a visible Gaussian has a radius of at least one pixel"
    means2d = torch.zeros(len(visible), 2, requires_grad=True)
    means2d.grad = grad_pixels
    ndc = torch.tensor([width / 2, height / 2])

    def positional_gradient(absolute=False):
        return ((grad_pixels.abs() * 2 if absolute else grad_pixels) * ndc).norm(dim=-1)

    info = SimpleNamespace(
        means2d=means2d,
        visible=visible,
        radii=torch.where(visible, radius, torch.zeros_like(radius)).int()[:, None].repeat(1, 2),  # 0: not seen
        width=width,
        height=height,
        means2d_absgrad=grad_pixels.abs() * 2,
        retain_absgrad=lambda: None,
        positional_gradient=positional_gradient,
    )
    # The render's own statistics kernel, on these tensors.
    info._gradient = functools.partial(RasterizeInfo._gradient, info)
    info.accumulate_statistics = functools.partial(RasterizeInfo.accumulate_statistics, info)
    return info


def context(model, optimizer, info, step, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return StepContext(
        step=step,
        total_steps=30000,
        model=model,
        optimizer=optimizer,
        info=info,
        view_index=0,
        extent=1.0,
        generator=generator,
    )


def tiny_config(scene, out, device=DEFAULT_DEVICE, **overrides):
    values = dict(
        data=DataConfig(data=scene),
        out=str(out),
        iters=40,
        device=device,
        eval_every=0,
        checkpoint_every=0,
        progress=False,
        sh_every=10,
    )
    values.update(overrides)
    return TrainConfig(**values)


def interrupt_at(monkeypatch, step: int, signum: int = signal.SIGINT) -> None:
    """Send the process ``signum`` (Ctrl-C's SIGINT by default) during iteration ``step``, after
    its update: the run stops there with a checkpoint of iteration ``step``."""
    real_step = Trainer.train_step

    def interrupted(self):
        result = real_step(self)
        if self.step == step:
            os.kill(os.getpid(), signum)
        return result

    monkeypatch.setattr(Trainer, "train_step", interrupted)


def train_argv(scene, out, iters: int, *extra: str, device: str = DEFAULT_DEVICE) -> list[str]:
    """`cdcgs train` arguments for a short run of ``scene`` into ``out``, without a progress bar."""
    return [
        "train",
        "--data",
        str(scene),
        "--out",
        str(out),
        "--iters",
        str(iters),
        "--no-progress",
        "--device",
        device,
        *extra,
    ]


# The short trainings that compare a way of stepping with the counted one (test_lookahead,
# test_graph): three densifications of SHORT's (at 20, 40 and 60).
ITERS = 60


def train_briefly(scene, out, strategy="3dgs", options=SHORT, **overrides):
    """An ``ITERS``-iteration training of ``scene`` into ``out`` (random background unless
    overridden): (the trainer, its result)."""
    from cdcgs.train.trainer import Trainer

    values = dict(iters=ITERS, log_every=25, background="random", strategy=strategy)
    values.update(overrides)
    trainer = Trainer(tiny_config(scene, out, **values), options)
    return trainer, trainer.run()


_TRAINED: dict = {}


def train_once(scene, out, strategy="3dgs", options=SHORT, **overrides):
    """:func:`train_briefly`, trained once per session for each set of arguments and shared by
    the tests that compare with it (the reference runs): callers only read it, and call it where no
    patch of theirs is in force. ``out`` is where the first call trains it."""
    key = (str(scene), strategy, repr(options), repr(sorted(overrides.items())))
    if key not in _TRAINED:
        _TRAINED[key] = train_briefly(scene, out, strategy, options, **overrides)
    return _TRAINED[key]


def assert_same_model(a, b) -> None:
    """Two trainers' parameters, Adam step counts and second moments equal bit for bit."""
    assert a.model.params.keys() == b.model.params.keys()
    for name in a.model.params:
        assert torch.equal(a.model.params[name], b.model.params[name]), name
    for p, q in zip(a.optimizer.param_groups, b.optimizer.param_groups):
        state_p, state_q = a.optimizer.state[p["params"][0]], b.optimizer.state[q["params"][0]]
        assert float(state_p["step"]) == float(state_q["step"])
        assert torch.equal(state_p["exp_avg_sq"], state_q["exp_avg_sq"]), p["name"]


def warp_without_ordinals(monkeypatch, ordinal: int) -> list:
    """Stand-ins, so that a test of a CUDA path runs on the CPU: torch's current GPU is
    ``ordinal``, and Warp's device_from_torch refuses ``cuda`` without an ordinal (as Warp 1.19
    does), answers "cuda:K" otherwise and records what it was asked (the list returned).
    cdcgs._interop's cache of Warp's answers is a fresh one for the test (the real one, untouched,
    comes back after it)."""
    import warp as wp

    from cdcgs import _interop

    monkeypatch.setattr(_interop, "_warp_device", functools.cache(_interop._warp_device.__wrapped__))
    monkeypatch.setattr(_interop, "ensure_warp", lambda: None)
    asked = []

    def device_from_torch(device):
        asked.append(device)
        if device.index is None:
            raise TypeError("no ordinal")
        return f"cuda:{device.index}"

    monkeypatch.setattr(wp, "device_from_torch", device_from_torch)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: ordinal)
    return asked
