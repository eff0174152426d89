"""Checkpoints: atomic writes, clear errors, and checkpoints of earlier versions."""

import json

import pytest
import torch
from helpers import DEFAULT_DEVICE, tiny_config, train_argv

from cdcgs.cli import main as cli_main
from cdcgs.errors import InputError
from cdcgs.io import load_checkpoint, save_checkpoint
from cdcgs.train.outputs import load_run
from cdcgs.train.trainer import CHECKPOINT_FORMAT, Trainer


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


def as_written_before_the_restructure(out) -> None:
    """Rewrite a run folder as cdcgs wrote it up to format 1 (checked against a real run of that
    version): global generator states in the checkpoint, the strategy named `adc`, save_maps among
    the strategy options, the viewer's options in the configuration."""
    path = out / "checkpoint.pt"
    state = torch.load(path, weights_only=False)
    del state["format"], state["checksum"]
    state["rng"] = {"python": None, "numpy": None, "torch": torch.get_rng_state()}
    state["strategy_options"] = {**state["strategy_options"], "save_maps": 4}
    state["config"].update(strategy="adc", view=False, view_port=8080, view_host="127.0.0.1")
    torch.save(state, path)
    config = json.load(open(out / "config.json"))
    config["train"].update(strategy="adc", view=False, view_port=8080, view_host="127.0.0.1")
    json.dump(config, open(out / "config.json", "w"))


def test_a_run_of_the_earlier_format_loads_and_resumes(tiny_scene, tmp_path):
    out = tmp_path / "run"
    Trainer(tiny_config(tiny_scene, out, iters=20), {"densify_from": 5, "densify_until": 15, "densify_every": 5}).run()
    as_written_before_the_restructure(out)
    run = load_run(out)
    assert run.config.strategy == "3dgs" and run.model.num > 0
    assert cli_main(["eval", str(out), "--device", DEFAULT_DEVICE]) == 0
    trainer = Trainer(tiny_config(tiny_scene, out, iters=25, resume=True))
    result = trainer.run()
    assert result["iterations"] == 25 and trainer.config.strategy == "3dgs"
    assert load_checkpoint(out / "checkpoint.pt")["format"] == CHECKPOINT_FORMAT


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda state: state.update(format=CHECKPOINT_FORMAT + 1), "written by a newer cdcgs"),
        (lambda state: state.pop("optimizer"), "not a cdcgs training checkpoint (no optimizer)"),
    ],
)
def test_checkpoints_this_version_cannot_resume_are_refused(tiny_scene, tmp_path, capsys, change, message):
    out = tmp_path / "run"
    Trainer(tiny_config(tiny_scene, out, iters=5)).run()
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    change(state)
    save_checkpoint(out / "checkpoint.pt", state)
    argv = train_argv(tiny_scene, out, 10, "--resume")
    assert cli_main(argv) == 2
    assert message in capsys.readouterr().err


def test_flipped_bytes_in_tensor_data_are_found(tmp_path):
    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"step": 3, "params": {"means": torch.arange(4096, dtype=torch.float32)}})
    data = bytearray(path.read_bytes())
    # The tensor's bytes are stored uncompressed inside the zip: flip one in the middle of them.
    start = bytes(data).index(torch.arange(4096, dtype=torch.float32).numpy().tobytes()[:64])
    data[start + 5000] ^= 0x10
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="does not match its checksum: the file is damaged"):
        load_checkpoint(path)


def test_a_failed_write_keeps_the_previous_checkpoint_and_says_so(tmp_path, monkeypatch):
    import errno

    path = tmp_path / "ckpt.pt"
    save_checkpoint(path, {"step": 1})

    def full_disk(obj, f):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(InputError, match=r"No space left on device\); the previous checkpoint is intact"):
        save_checkpoint(path, {"step": 2})
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 1 and sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]


def test_non_finite_state_is_refused_and_never_exported(tiny_scene, tmp_path, capsys):
    out = tmp_path / "run"
    Trainer(tiny_config(tiny_scene, out, iters=5)).run()
    state = torch.load(out / "checkpoint.pt", weights_only=False)
    state["model"]["params"]["means"][0, 0] = float("nan")
    save_checkpoint(out / "checkpoint.pt", state)  # a valid checksum over bad values
    (out / ".checkpoint.pt.tmp-999999").write_bytes(b"left by a killed write")
    argv = ["train", "--data", str(tiny_scene), "--out", str(out), "--iters", "10", "--resume", "--no-progress"]
    assert cli_main([*argv, "--device", DEFAULT_DEVICE]) == 2
    err = capsys.readouterr().err
    assert "holds NaN or infinite values (model means): it cannot be resumed" in err, err
    assert not (out / ".checkpoint.pt.tmp-999999").exists(), "leftover temporary files are cleaned on the next start"
    assert cli_main(["export", str(out), str(tmp_path / "m.ply")]) == 2
    assert "hold NaN or infinite values: not exported" in capsys.readouterr().err
    assert not (tmp_path / "m.ply").exists()
    assert cli_main(["export", str(out), str(tmp_path)]) == 2
    assert "is a folder; give the PLY file to write" in capsys.readouterr().err
