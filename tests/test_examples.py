"""The examples double as smoke tests with a few iterations."""

import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_train_garden_example_runs(tmp_path, device):
    out = tmp_path / "garden"
    result = subprocess.run(
        [sys.executable, "examples/train_garden.py", "--device", device, "--out", str(out),
         "--gaussians", "1500", "--views", "2", "--steps", "10"],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"outputs in {out}" in result.stdout
    assert sorted(p.name for p in out.iterdir()) == ["fitted_view_00.png", "view_00.png", "view_01.png"]
    psnrs = [float(line.split("PSNR to view 0 ")[1].split()[0]) for line in result.stdout.splitlines() if "PSNR" in line]
    assert psnrs[1] > psnrs[0] + 1.5, result.stdout


def test_train_garden_rejects_bad_options(tmp_path):
    result = subprocess.run(
        [sys.executable, "examples/train_garden.py", "--gaussians", "0", "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert result.returncode == 2 and "--gaussians and --views must be positive" in result.stderr


def test_warp_launch_example_writes_png(tmp_path, device):
    out = tmp_path / "ring.png"
    result = subprocess.run(
        [sys.executable, "examples/warp_launch.py", "--device", device, "--out", str(out)], cwd=ROOT, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert out.stat().st_size > 1000
