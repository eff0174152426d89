"""The examples double as smoke tests with a few iterations."""

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_train_garden_falls_back_to_the_procedural_scene(tmp_path, device):
    out = tmp_path / "garden"
    result = subprocess.run(
        [
            sys.executable,
            "examples/train_garden.py",
            "--data",
            str(tmp_path / "absent"),
            "--out",
            str(out),
            "--iters",
            "20",
            "--device",
            device,
            "--no-progress",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "cdcgs download mipnerf360 --scene garden" in result.stdout
    assert f"outputs in {out}" in result.stdout
    metrics = json.load(open(out / "metrics.json"))
    assert metrics["iterations"] == 20 and metrics["test"]["views"] == 5
    assert os.path.isdir(out / "procedural_scene" / "sparse" / "0")


def test_train_garden_rejects_bad_options(tmp_path):
    result = subprocess.run(
        [sys.executable, "examples/train_garden.py", "--iters", "0", "--out", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2 and "--iters must be positive" in result.stderr


def test_warp_launch_example_writes_png(tmp_path, device):
    out = tmp_path / "ring.png"
    result = subprocess.run(
        [sys.executable, "examples/warp_launch.py", "--device", device, "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert out.stat().st_size > 1000
