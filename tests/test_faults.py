"""Faults injected into trainings on the tiny procedural scene: SIGINT and SIGTERM at every kind
of moment (a real signal, sent by the process to itself or by another process), a second signal
during the save, and NaN or exploding numbers. The resumed runs are compared byte for byte with
an uninterrupted one."""

import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from helpers import DEFAULT_DEVICE, SHORT, interrupt_at, tiny_config, train_argv

import cdcgs.io.checkpoint as checkpoint_module
import cdcgs.train.trainer as trainer_module
from cdcgs.cli import main as cli_main
from cdcgs.io import load_checkpoint
from cdcgs.train.cdc import CDC
from cdcgs.train.config import LearningRates
from cdcgs.train.guard import EXPLODE_FACTOR, EXPLODE_FLOOR, SMOOTHING, NumericGuard
from cdcgs.train.trainer import Interrupted, Trainer, TrainingDiverged

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CPU_ONLY = pytest.mark.skipif(
    DEFAULT_DEVICE != "cpu", reason="byte-identical runs on the CPU only: on CUDA the order of float atomic adds varies"
)
ITERS = 60
# Densification at 20, 30, 40, 50, 60; evaluation at 25; a checkpoint every 30.
OPTIONS = {**SHORT, "densify_from": 10, "densify_every": 10}


def config(scene, out, **overrides):
    values = dict(iters=ITERS, eval_every=25, checkpoint_every=30, background="random")
    values.update(overrides)
    return tiny_config(scene, out, **values)


@pytest.fixture(scope="module")
def straight(tiny_scene, tmp_path_factory):
    """The PLY of the uninterrupted run."""
    out = tmp_path_factory.mktemp("straight")
    Trainer(config(tiny_scene, out), OPTIONS).run()
    return (out / "point_cloud.ply").read_bytes()


def resume(scene, out) -> bytes:
    Trainer(config(scene, out, resume=True), OPTIONS).run()
    return (out / "point_cloud.ply").read_bytes()


def send_during(monkeypatch, owner, name: str, signum: int, at: int = 1) -> None:
    """Send the process ``signum`` at the start of the ``at``-th call of ``owner.name``."""
    real = getattr(owner, name)
    calls = {"n": 0}

    def wrapped(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == at:
            os.kill(os.getpid(), signum)
        return real(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapped)


@CPU_ONLY
@pytest.mark.parametrize(
    "moment,signum,stops_at",
    [
        ("densification", signal.SIGTERM, 20),  # the first densification, iteration 20
        ("evaluation", signal.SIGINT, 25),  # the periodic evaluation after iteration 25
        ("checkpoint write", signal.SIGTERM, 30),  # the periodic checkpoint of iteration 30
        ("loss", signal.SIGINT, 33),  # in the middle of iteration 33, before its backward pass
    ],
)
def test_a_signal_at_any_moment_stops_at_an_iteration_and_resumes_byte_identically(
    tiny_scene, tmp_path, monkeypatch, straight, moment, signum, stops_at
):
    with monkeypatch.context() as patch:
        if moment == "densification":
            send_during(patch, CDC, "densify_and_prune", signum)
        elif moment == "evaluation":
            send_during(patch, trainer_module, "evaluate", signum)
        elif moment == "checkpoint write":
            send_during(patch, trainer_module, "save_checkpoint", signum)
        else:
            send_during(patch, trainer_module, "fused_photometric_loss", signum, at=stops_at)
        with pytest.raises(Interrupted) as stop:
            Trainer(config(tiny_scene, tmp_path), OPTIONS).run()
    assert stop.value.clean and stop.value.signum == signum and stop.value.exit_status == 128 + signum
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["step"] == stops_at, "the checkpoint counts exactly the iterations whose updates it holds"
    assert (tmp_path / "point_cloud.ply").exists() and not (tmp_path / ".lock").exists()
    assert resume(tiny_scene, tmp_path) == straight, f"resumed after a {moment} signal: not the uninterrupted run"


@CPU_ONLY
def test_a_second_signal_during_the_save_corrupts_nothing(tiny_scene, tmp_path, monkeypatch, straight, capsys):
    with monkeypatch.context() as patch:
        interrupt_at(patch, 40, signal.SIGTERM)
        real_save = torch.save
        saves = {"n": 0}

        def killed_save(obj, f, *args, **kwargs):  # the periodic save at 30 goes through; the next is cut
            saves["n"] += 1
            if saves["n"] == 1:
                return real_save(obj, f, *args, **kwargs)
            f.write(b"the first bytes of a checkpoint")
            os.kill(os.getpid(), signal.SIGTERM)
            raise AssertionError("the second signal must stop the save at once")

        patch.setattr(checkpoint_module.torch, "save", killed_save)
        with pytest.raises(Interrupted) as stop:
            Trainer(config(tiny_scene, tmp_path), OPTIONS).run()
    assert not stop.value.clean
    assert "stopped at once by SIGTERM: nothing more written" in capsys.readouterr().out
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 30, "the previous checkpoint, whole"
    assert sorted(os.listdir(tmp_path)) == ["checkpoint.pt", "config.json", "test_views.txt"], (
        "no temporary file, no half PLY"
    )
    assert resume(tiny_scene, tmp_path) == straight


@CPU_ONLY
def test_sigterm_from_another_process_then_resume_is_the_same_run(tiny_scene, tmp_path, straight):
    out = tmp_path / "run"
    argv = [
        *train_argv(tiny_scene, out, ITERS, device="cpu"),
        "--eval-every",
        "25",
        "--checkpoint-every",
        "30",
        "--background",
        "random",
        "--sh-every",
        "10",
        *(f"--{k.replace('_', '-')}={v}" for k, v in OPTIONS.items()),
    ]
    env = {**os.environ, "PYTHONPATH": ROOT}
    process = subprocess.Popen(
        [sys.executable, "-m", "cdcgs", *argv], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    # Once the first checkpoint is there, training is under way: stop it where it happens to be.
    deadline = time.monotonic() + 120
    while not (out / "checkpoint.pt").exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr.decode()
    step = load_checkpoint(out / "checkpoint.pt")["step"]
    assert 30 <= step < ITERS
    assert f"stopped by SIGTERM at iteration {step}: checkpoint and PLY written" in stdout.decode()
    assert not (out / ".lock").exists()
    assert resume(tiny_scene, out) == straight


class NanGradient(torch.autograd.Function):
    """The identity forward; NaN gradients backward."""

    @staticmethod
    def forward(ctx, x):
        return x.view_as(x)

    @staticmethod
    def backward(ctx, grad):
        return grad * float("nan")


def poison_loss(monkeypatch, at: int, how: str) -> None:
    """At the ``at``-th loss of the run: a NaN loss, or a finite loss with NaN gradients."""
    real = trainer_module.fused_photometric_loss
    calls = {"n": 0}

    def poisoned(image, target, weight):
        calls["n"] += 1
        if calls["n"] != at:
            return real(image, target, weight)
        if how == "loss":
            loss, mse = real(image, target, weight)
            return loss * float("nan"), mse
        return real(NanGradient.apply(image), target, weight)

    monkeypatch.setattr(trainer_module, "fused_photometric_loss", poisoned)


@pytest.mark.parametrize("how, sync", [("loss", ""), ("gradients", ""), ("gradients", "--sync-free")])
def test_nan_stops_the_run_and_keeps_the_last_good_checkpoint(tiny_scene, tmp_path, monkeypatch, capsys, how, sync):
    """Also with --sync-free, where the render of iteration 34 flags the NaN on the device and the
    run finds it at its next read (the log of iteration 50), goes back to 34 and stops the same."""
    poison_loss(monkeypatch, 33, how)
    argv = [*train_argv(tiny_scene, tmp_path, ITERS), "--checkpoint-every", "30", "--eval-every", "0"]
    argv += [sync] if sync else []
    assert cli_main(argv) == 3
    message = capsys.readouterr().err
    # NaN gradients (from a NaN loss or not) make the parameters NaN in that iteration's update,
    # which the next render finds.
    assert "training stopped at iteration 33: the update of iteration 33 made means, log_scales" in message
    assert "The learning rates in force: means " in message and "sh_dc 0.0025" in message
    assert f"The last good state, iteration 30, is in {tmp_path / 'checkpoint.pt'}" in message
    state = load_checkpoint(tmp_path / "checkpoint.pt")
    assert state["step"] == 30 and all(torch.isfinite(p).all() for p in state["model"]["params"].values())
    assert not (tmp_path / "point_cloud.ply").exists(), "nothing of the bad state is written"
    monkeypatch.undo()
    assert cli_main([*argv, "--resume"]) == 0, "the last good checkpoint resumes"


def test_an_exploding_loss_stops_the_run_and_names_the_learning_rates(tiny_scene, tmp_path):
    trainer = Trainer(config(tiny_scene, tmp_path, lr=LearningRates(sh_dc=1e3), log_every=5), OPTIONS)
    with pytest.raises(TrainingDiverged, match=r"the loss exploded \(running mean .* at iteration \d+, against") as err:
        trainer.run()
    assert "sh_dc 1e+03" in str(err.value) and "No checkpoint had been written yet" in str(err.value)
    assert sorted(os.listdir(tmp_path)) == ["config.json", "test_views.txt"]


def test_non_finite_parameters_are_named(tiny_scene, tmp_path, monkeypatch):
    real_step = Trainer.train_step

    def corrupting(self):
        log = real_step(self)
        if self.step == 12:
            with torch.no_grad():
                self.model.params["opacity_logits"][3] = float("inf")
        return log

    monkeypatch.setattr(Trainer, "train_step", corrupting)
    # An infinite logit renders as opacity 1, so the render does not see it; the check before the
    # checkpoint of iteration 20 does, and that checkpoint is not written.
    with pytest.raises(TrainingDiverged, match=r"iteration 20: the parameters opacity_logits hold NaN or infinite"):
        Trainer(config(tiny_scene, tmp_path, checkpoint_every=10, eval_every=0), OPTIONS).run()
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 10


def test_the_guard_records_without_reading_the_device_and_trips_as_computed_by_hand(monkeypatch):
    losses = [0.30, 0.28, 0.31, 0.9, 2.5, 4.0, 9.0, 30.0]
    optimizer = torch.optim.Adam([{"params": [torch.zeros(1, requires_grad=True)], "lr": 0.5, "name": "means"}])
    guard = NumericGuard("cpu")
    mean, limit, tripped = None, max(EXPLODE_FACTOR * losses[0], EXPLODE_FLOOR), []
    for step, loss in enumerate(losses, start=1):
        with monkeypatch.context() as patch:
            for method in ("tolist", "item", "__bool__", "__float__", "__int__", "numpy"):
                patch.setattr(torch.Tensor, method, lambda *a, **k: pytest.fail("a host read during record()"))
            guard.record(torch.tensor(loss), torch.tensor(20.0))
        # By hand, in float64: the running mean, and whether it passed the limit.
        mean = loss if mean is None else SMOOTHING * mean + (1 - SMOOTHING) * loss
        assert guard.means()[0] == pytest.approx(mean, rel=1e-6)
        try:
            guard.check(step, optimizer)
        except TrainingDiverged as err:
            assert f"the loss exploded (running mean {mean:.4g} at iteration {step}" in str(err)
            assert "means 0.5" in str(err)
            tripped.append(step)
        assert (step in tripped) == (mean > limit), f"loss {step}: running mean {mean}, limit {limit}"
    # The mean rises past 0.9 at the 4th loss without a stop; it passes 1.5 at the 7th (1.72).
    assert tripped == [7, 8]
    nan = NumericGuard("cpu")
    nan.record(torch.tensor(0.3), torch.tensor(20.0))
    nan.record(torch.tensor(float("nan")), torch.tensor(20.0))
    with pytest.raises(TrainingDiverged, match="the loss became NaN or infinite"):
        nan.check(2, optimizer)
    fine = NumericGuard("cpu")
    fine.record(torch.tensor(0.3), torch.tensor(20.0))
    with pytest.raises(TrainingDiverged, match="the parameters b hold NaN or infinite values"):
        fine.check(1, optimizer, {"a": torch.ones(3), "b": torch.tensor([1.0, float("inf")])})


def test_the_numbers_are_read_only_at_log_steps_refinements_saves_and_evaluations(tiny_scene, tmp_path, monkeypatch):
    steps = []
    real = NumericGuard.check

    def spy(self, step, *args, **kwargs):
        steps.append(step)
        return real(self, step, *args, **kwargs)

    monkeypatch.setattr(NumericGuard, "check", spy)
    # 40 iterations, curves every 10, densification at 40 (SHORT), no periodic evaluation or checkpoint.
    Trainer(tiny_config(tiny_scene, tmp_path, iters=40, log_every=10), SHORT).run()
    # log steps 10, 20, 30, 40; the densification of 40; the final checkpoint and evaluation.
    assert steps == [10, 20, 30, 40, 40, 40, 40]


def test_a_signal_while_the_scene_loads_stops_at_once_and_leaves_nothing(tiny_scene, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    send_during(monkeypatch, trainer_module, "load_scene", signal.SIGTERM)
    with pytest.raises(Interrupted) as stop:
        Trainer(config(tiny_scene, out), OPTIONS).run()
    assert not stop.value.clean and stop.value.exit_status == 143
    assert "stopped at once by SIGTERM: no checkpoint was written" in capsys.readouterr().out
    assert not out.exists(), "the folder this run created, still empty, is removed (lock included)"
