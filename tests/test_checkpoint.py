"""Checkpoints: atomic writes, clear errors, and a resumed run that continues the same run."""

import random

import numpy as np
import pytest
import torch

from cdcgs.errors import InputError
from cdcgs.io import capture_rng_state, load_checkpoint, restore_rng_state, save_checkpoint


def test_round_trip(tmp_path):
    state = {"step": 7, "params": {"means": torch.randn(5, 3)}, "config": {"lr": 0.1}}
    save_checkpoint(tmp_path / "ckpt.pt", state)
    back = load_checkpoint(tmp_path / "ckpt.pt")
    assert back["step"] == 7 and torch.equal(back["params"]["means"], state["params"]["means"])


def test_crash_while_saving_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"step": 1})

    def crashing_save(obj, f):
        f.write(b"partial bytes")
        raise KeyboardInterrupt("killed while saving")

    monkeypatch.setattr(torch, "save", crashing_save)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, {"step": 2})
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"], "the temporary file must be cleaned up"


@pytest.mark.parametrize("content", [b"", b"garbage bytes", None])
def test_bad_checkpoints(tmp_path, content):
    path = tmp_path / "ckpt.pt"
    if content is None:
        torch.save([1, 2, 3], path)
        match = "not a cdcgs checkpoint"
    else:
        path.write_bytes(content)
        match = "not a readable checkpoint"
    with pytest.raises(InputError, match=match):
        load_checkpoint(path)
    with pytest.raises(InputError, match="no checkpoint file"):
        load_checkpoint(tmp_path / "other.pt")


def test_truncated_checkpoint(tmp_path):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"x": torch.randn(1000)})
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(InputError, match="not a readable checkpoint"):
        load_checkpoint(path)


def _noisy_training(steps, state=None):
    """A toy run that draws from every generator: resuming must reproduce it exactly."""
    if state is None:
        torch.manual_seed(0)
        np.random.seed(0)
        random.seed(0)
        param = torch.nn.Parameter(torch.zeros(4))
        optimizer = torch.optim.Adam([param], lr=0.1)
        start = 0
    else:
        param = torch.nn.Parameter(state["param"])
        optimizer = torch.optim.Adam([param], lr=0.1)
        optimizer.load_state_dict(state["optimizer"])
        restore_rng_state(state["rng"])
        start = state["step"]
    for _ in range(start, steps):
        target = torch.randn(4) + np.random.rand() + random.random()
        loss = ((param - target) ** 2).sum()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return param, optimizer


def test_resume_continues_the_same_run(tmp_path):
    straight, _ = _noisy_training(20)
    param, optimizer = _noisy_training(10)
    save_checkpoint(tmp_path / "ckpt.pt", {"param": param.detach().clone(), "optimizer": optimizer.state_dict(), "rng": capture_rng_state(), "step": 10})
    random.random(), np.random.rand(), torch.randn(3)  # disturb the generators in between
    resumed, _ = _noisy_training(20, load_checkpoint(tmp_path / "ckpt.pt"))
    assert torch.equal(resumed, straight)
