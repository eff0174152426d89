"""The benchmark suite runs end to end (on the CPU, tiny sizes) and sorts kernels into stages."""

import argparse
import json
import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import cdcgs.render
from cdcgs.datasets.procedural import make_procedural_scene
from cdcgs.train import DataConfig, TrainConfig, Trainer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
import run as suite  # noqa: E402

WORKLOAD = """
import math, torch

def make_scene(n, device="cpu"):
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * 0.5 + torch.tensor([0.0, 0.0, 4.0])
    K = torch.tensor([[40.0, 0, 24.0], [0, 40.0, 18.0], [0, 0, 1]])
    return {
        "means": means.to(device), "quats": torch.randn(n, 4, generator=g).to(device),
        "scales": (torch.rand(n, 3, generator=g) * 0.05 + 0.01).to(device),
        "opacities": torch.rand(n, generator=g).to(device), "sh": (torch.randn(n, 16, 3, generator=g) * 0.3).to(device),
        "viewmat": torch.eye(4).to(device), "K": K.to(device), "width": 48, "height": 36, "sh_degree": 3,
    }
"""


@pytest.mark.parametrize(
    "kernel,stage",
    [
        ("project_gaussians_kernel_3c72d62f_cuda_kernel_forward", "projection"),
        ("project_gaussians_kernel_3c72d62f_cuda_kernel_backward", "projection backward"),
        ("sh_to_color_kernel_4c707bbf_cuda_kernel_forward", "sh colour"),
        ("sh_to_color_kernel_4c707bbf_cuda_kernel_backward", "sh colour backward"),
        ("emit_keys_kernel_1a2b_cuda_kernel_forward", "binning + sort"),
        ("gather_counts_kernel_1a2b_cuda_kernel_forward", "binning + sort"),
        ("void cub::DeviceRadixSortOnesweepKernel<cub::DeviceRadixSortPolicy>", "binning + sort"),
        ("blend_forward_kernel_66825d96_cuda_kernel_forward", "blend forward"),
        ("blend_backward_kernel_30912936_cuda_kernel_forward", "blend backward"),
        ("_blend_backward__locals__blend_backward_kernel_762ac5e6_cuda_kernel_forward", "blend backward"),
        ("void gsplat::projection_ewa_3dgs_fused_fwd_kernel<float>(...)", "projection"),
        ("void gsplat::projection_ewa_3dgs_fused_bwd_kernel<float>(...)", "projection backward"),
        ("void gsplat::spherical_harmonics_bwd_kernel<float>(...)", "sh colour backward"),
        ("void gsplat::intersect_tile_kernel<float>(...)", "binning + sort"),
        ("void gsplat::rasterize_to_pixels_3dgs_fwd_kernel<3u, float>(...)", "blend forward"),
        ("void gsplat::rasterize_to_pixels_3dgs_bwd_kernel<3u, float>(...)", "blend backward"),
        ("void at::native::vectorized_elementwise_kernel<4, at::native::FillFunctor<float>>", "other (torch)"),
        ("ssim_l1_forward_kernel_5e1f_cuda_kernel_forward", "loss (L1 + D-SSIM)"),
        ("ssim_l1_backward_kernel_5e1f_cuda_kernel_forward", "loss (L1 + D-SSIM)"),
        ("ssim_l1_forward_rows_kernel_b205_cuda_kernel_forward", "loss (L1 + D-SSIM)"),
        ("ssim_l1_backward_rows_kernel_7a53_cuda_kernel_forward", "loss (L1 + D-SSIM)"),
    ],
)
def test_kernels_sort_into_stages(kernel, stage):
    assert suite.stage_of(kernel) == stage


def test_suite_runs_and_writes_one_json(tmp_path, capsys):
    workload = tmp_path / "workload.py"
    workload.write_text(WORKLOAD)
    scene = make_procedural_scene(tmp_path / "scene", views=8, width=48, height=36, points=300)
    run_dir = tmp_path / "run"
    config = TrainConfig(
        data=DataConfig(data=scene),
        out=str(run_dir),
        iters=10,
        device="cpu",
        eval_every=0,
        checkpoint_every=0,
        progress=False,
        save_renders=False,
    )
    Trainer(config, {"densify_from": 10**6}).run()
    out = tmp_path / "suite.json"
    suite.main(
        [
            "--device",
            "cpu",
            "--sections",
            "raster",
            "knn",
            "complexity",
            "training",
            "--sizes",
            "300",
            "--knn-sizes",
            "2000",
            "--iters",
            "2",
            "--warmup",
            "1",
            "--workload",
            str(workload),
            "--training-run",
            str(run_dir),
            "--peer-training",
            os.path.join(ROOT, "benchmarks", "peers", "gsplat_bonsai.json"),
            "--out",
            str(out),
        ]
    )
    report = json.loads(out.read_text())
    sections = [row["section"] for row in report["rows"]]
    assert {"raster", "knn", "complexity", "training"} <= set(sections)
    raster = next(r for r in report["rows"] if r["section"] == "raster")
    assert (
        raster["n"] == 300
        and raster["forward_ms"] > 0
        and raster["forward_backward_ms"] > 0
        and raster["intersections"] > 0
    )
    training = [r for r in report["rows"] if r["section"] == "training"]
    with open(os.path.join(ROOT, "benchmarks", "peers", "gsplat_bonsai.json")) as f:
        quoted = json.load(f)
    assert training[0]["iterations"] == 10 and training[1]["psnr"] == quoted["psnr"]  # quoted as it stands
    printed = capsys.readouterr().out
    assert "## cdcgs benchmark suite on cpu" in printed and "| training run |" in printed


def test_step_profile_runs_on_a_scene_and_counts_every_part(tmp_path, capsys, monkeypatch):
    import profile_step

    scene = make_procedural_scene(tmp_path / "scene", views=8, width=48, height=36, points=300)
    out = tmp_path / "profile.json"
    argv = ["--data", str(scene), "--gaussians", "200", "500", "--steps", "2", "--warmup", "1", "--out", str(out)]
    assert profile_step.main([*argv, "--at", "501", "--complexity-views", "2"]) == 0  # during densification
    rows = json.loads(out.read_text())["rows"]
    assert [row["gaussians"] for row in rows] == [200, 500], "resampled down and up to the counts asked"
    for row in rows:
        assert row["wall_ms_per_step"] > 0
        assert set(row["parts"]) == {*profile_step.PARTS, "rest of the step"}, "every part is labelled and seen"
        # Every part is timed by the clock of the wall-clock window (the profiler's CPU time, which
        # this replaced, read 0 for most of them on a GPU), and together they are that window.
        assert all(row["parts"][part]["host_ms"] > 0 for part in profile_step.PARTS)
        parts_ms = sum(part["host_ms"] for part in row["parts"].values())
        assert parts_ms == pytest.approx(row["wall_ms_per_step"], rel=1e-6)
        assert row["complexity_pass"]["views"] == 2 and row["complexity_pass"]["wall_ms_per_view"] > 0
        assert row["complexity_pass"]["wall_ms_per_view_one_at_a_time"] > 0
    printed = capsys.readouterr().out
    assert "| ms per step (wall) |" in printed and "| Γ pass: ms per view (wall), one view at a time |" in printed
    # The chunked blend adjoint through a whole step (BLEND_CHUNK restored after), and a bad chunk refused.
    default = cdcgs.render.BLEND_CHUNK
    assert profile_step.main([*argv, "--blend-chunk", "512"]) == 0 and default == cdcgs.render.BLEND_CHUNK
    with pytest.raises(SystemExit):
        profile_step.main([*argv, "--blend-chunk", "100"])
    # The Γ pass with w_max scattered: in force during the run, as it was after.
    import cdcgs.complexity as complexity

    seen, real = [], complexity.gaussian_complexity

    def spy(*args, **kwargs):
        seen.append(complexity.W_MAX_PASS)
        return real(*args, **kwargs)

    monkeypatch.setattr(complexity, "gaussian_complexity", spy)
    assert profile_step.main([*argv, "--complexity-views", "2", "--w-max-pass", "scatter"]) == 0
    assert seen and set(seen) == {"scatter"}
    assert complexity.W_MAX_PASS == "walk", "restored"
    # 3DGS-MCMC's step (its noise and regularisers), at the profiled count as its budget.
    mcmc = tmp_path / "mcmc.json"
    assert (
        profile_step.main(
            [*argv[:2], "--gaussians", "200", "--steps", "1", "--warmup", "1", "--strategy", "mcmc", "--out", str(mcmc)]
        )
        == 0
    )
    (row,) = json.loads(mcmc.read_text())["rows"]
    assert row["gaussians"] == 200 and row["parts"]["strategy after step"]["host_ms"] > 0

    def one_row(name: str, *flags: str) -> dict:
        """The single row of a 200-Gaussian profile with ``flags``, two steps a window."""
        path = tmp_path / f"{name}.json"
        common = ["--gaussians", "200", "--steps", "2", "--warmup", "1", "--out", str(path)]
        assert profile_step.main([*argv[:2], *common, *flags]) == 0
        (row,) = json.loads(path.read_text())["rows"]
        return row

    # The --sync-free step: every render of the windows goes into slots and none reads its count;
    # the window's one read is a part of its own.
    row = one_row("free", "--sync-free")
    assert row["sync_free"]["renders_counted"] == 0 and row["sync_free"]["renders_within_capacity"] == 1 + 3 * 2
    assert "intersection count (sync)" not in row["parts"] and row["parts"]["sync-free read"]["host_ms"] > 0
    # The --cuda-graph step: on the CPU its steps run one operation at a time, and are counted. The
    # warm-up step runs as before (Adam's first step makes the moments a graph names); the windows replay.
    row = one_row("graph", "--cuda-graph")
    assert row["cuda_graph"]["replayed_steps"] == 3 * 2 and row["sync_free"]["renders_counted"] == 0
    boxes = tmp_path / "boxes.json"
    assert profile_step.main([*argv[:-1], str(boxes), "--rectangles", "--reference-loss"]) == 0
    for exact, box in zip(rows, json.loads(boxes.read_text())["rows"]):
        assert box["intersections"] > exact["intersections"] > 0, "whole rectangles hold more pairs"


def test_part_clock_counts_each_part_less_the_parts_inside_it(monkeypatch):
    import profile_step

    now = [0.0]
    monkeypatch.setattr(profile_step.time, "perf_counter", lambda: now[0])
    clock = profile_step.PartClock()

    def advance(seconds):
        now[0] += seconds

    inner = clock.wrap("inner", advance)

    def outer_work():
        advance(3.0)
        inner(2.0)
        advance(1.0)

    outer = clock.wrap("outer", outer_work)
    outer()
    outer()
    inner(0.5)  # alone: all of it is the inner part's
    assert clock.seconds == {"outer": 8.0, "inner": 4.5}


def test_host_overhead_reports_the_step_its_parts_and_the_profile(capsys):
    import host_overhead

    argv = ["--gaussians", "100", "--size", "32", "24", "--steps", "3", "--warmup", "1", "--top", "5"]
    assert host_overhead.main(argv) == 0
    printed = capsys.readouterr().out
    assert "ms per step:" in printed and "host ms per step:" in printed
    parts = dict(
        line.strip("| ").split(" | ") for line in printed.splitlines() if line.startswith("| ") and line.count("|") == 3
    )
    for part in ["render forward", "backward", "optimizer step", host_overhead.KERNELS]:
        assert float(parts[part]) > 0, part
    assert "cdcgs/train/trainer.py" in printed and "train_step" in printed, "the profile names the trainer's functions"


def test_training_table_counts_the_processes_on_the_gpu_with_nvidia_smi(tmp_path, monkeypatch):
    """gpu_process_count asks nvidia-smi for the compute processes of one GPU (an index or a UUID,
    the first of CUDA_VISIBLE_DEVICES) and counts its lines; None where it is missing or fails."""
    import training_table

    fake = tmp_path / "bin"
    fake.mkdir()
    script = fake / "nvidia-smi"
    script.write_text(f'#!/bin/sh\necho "$@" > "${{0%/*}}/args"\nprintf "4242\\n777\\n{os.getpid()}\\n"\n')
    script.chmod(0o755)
    monkeypatch.setenv("PATH", str(fake))
    assert training_table.gpu_process_count("GPU-1234") == 2, "the table's own process is not counted"
    assert "--query-compute-apps=pid" in (fake / "args").read_text() and "--id=GPU-1234" in (fake / "args").read_text()
    script.write_text("#!/bin/sh\nexit 9\n")
    assert training_table.gpu_process_count("0") is None
    script.unlink()
    assert training_table.gpu_process_count("0") is None
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", " 3,1")
    assert training_table.visible_gpu() == "3"
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert training_table.visible_gpu() == "0"


def test_a_stopped_table_stops_every_process_of_the_run(tmp_path, monkeypatch):
    """Ctrl-C (or a failed look) while a run is watched stops the run's whole process group, as
    torchrun's workers need: here a child and the grandchild it started."""
    import training_table

    pidfile = tmp_path / "grandchild"
    child = (
        "import subprocess, sys, time; "
        "g = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']); "
        f"open({str(pidfile)!r}, 'w').write(str(g.pid)); time.sleep(60)"
    )

    def look(gpu):
        if pidfile.exists() and pidfile.read_text():
            raise KeyboardInterrupt
        return 1

    monkeypatch.setattr(training_table, "gpu_process_count", look)
    start = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        training_table.run_watched([sys.executable, "-c", child], ["0"], every=0.1)
    grandchild = int(pidfile.read_text())

    def alive(pid):
        try:
            with open(f"/proc/{pid}/status") as f:
                return "\tZ" not in next(line for line in f if line.startswith("State:"))
        except FileNotFoundError:
            return False

    while alive(grandchild) and time.monotonic() - start < 20:
        time.sleep(0.1)
    assert not alive(grandchild), "the run's grandchild outlived the table"


def test_training_table_says_which_runs_shared_their_gpu(monkeypatch):
    """A timed run is watched while it lasts: the most processes seen beside it on its GPU, or
    None when no look saw it there (not checked); the table marks the runs that shared their GPU
    and does not call them alone, nor their ratio to gsplat a timing."""
    import training_table

    counts = iter([0, 1, 3, 1] + [1] * 10_000)  # starting (not there yet), alone, beside two others, alone
    monkeypatch.setattr(training_table, "gpu_process_count", lambda gpu: next(counts))
    status, seen = training_table.run_watched([sys.executable, "-c", "import time; time.sleep(1.0)"], ["3"], every=0.05)
    assert status == 0 and seen["gpus"] == ["3"] and seen["looks"] >= 3 and seen["most_others"] == 2
    monkeypatch.setattr(training_table, "gpu_process_count", lambda gpu: None)
    status, seen = training_table.run_watched([sys.executable, "-c", "import sys; sys.exit(3)"], ["0"], every=0.05)
    assert status == 3 and seen == {"gpus": ["0"], "looks": 0, "most_others": None}
    # On several GPUs: the largest count beyond the run's own process on any of them.
    counts = {"0": iter([1] * 10_000), "1": iter([0, 2] + [1] * 10_000)}
    monkeypatch.setattr(training_table, "gpu_process_count", lambda gpu: next(counts[gpu]))
    status, seen = training_table.run_watched(
        [sys.executable, "-c", "import time; time.sleep(0.5)"], ["0", "1"], every=0.05
    )
    assert status == 0 and seen["most_others"] == 1 and seen["looks"] >= 2

    base = {"train_seconds": 10.0, "iterations_per_second": 3.0, "test": {"psnr": 30.0}, "num_gaussians": 5}
    rows = {name: {**base, "neighbours": {"most_others": 0}} for name in ("3dgs", "cdc", "gsplat")}
    rows["cdc"]["neighbours"]["most_others"] = 2
    text = training_table.table(rows, "an H100", 100, "bonsai", None)
    assert "cdc shared the GPU with other processes (marked †): their times are not timings" in text
    assert "| cdc † |" in text and "| 3dgs |" in text and "each alone on its GPU" not in text
    assert "`3dgs` took 1.00× gsplat's training time.\n" in text
    assert "`cdc` took 1.00× gsplat's training time (not a timing: one of the two shared its GPU)." in text
    rows["cdc"]["neighbours"]["most_others"] = 0
    text = training_table.table(rows, "an H100", 100, "bonsai", None)
    assert "one after another on an H100, each alone on its GPU (nvidia-smi looked every 5 s)" in text
    del rows["cdc"]["neighbours"]  # a run trained before the watch, or where it saw nothing
    text = training_table.table(rows, "an H100", 100, "bonsai", None)
    assert "not checked for other processes on the GPU: cdc" in text and "each alone" not in text


def test_training_table_trains_each_run_alone_and_writes_the_table_into_the_docs(tmp_path, capsys):
    import training_table

    scene = make_procedural_scene(tmp_path / "scene", views=6, width=32, height=24, points=200)
    docs = tmp_path / "bench.md"
    docs.write_text(f"# Bench\n\nbefore\n{training_table.BEGIN}\nold table\n{training_table.END}\nafter\n")
    out = tmp_path / "runs"
    argv = ["--data", str(scene), "--out", str(out), "--runs", "3dgs", "gsplat", "--iters", "12", "--docs", str(docs)]
    assert training_table.main([*argv, "--train-option=--device=cpu"]) == 0
    metrics = json.loads((out / "3dgs" / "metrics.json").read_text())
    assert metrics["iterations"] == 12 and not (out / ".warm-3dgs").exists()
    text = docs.read_text()
    assert "old table" not in text and text.startswith("# Bench\n\nbefore\n") and text.endswith("after\n")
    row = next(line for line in text.splitlines() if line.startswith("| 3dgs |"))
    assert f"{metrics['num_gaussians']:,}" in row and f"{metrics['test']['psnr']:.2f}" in row
    assert "| gsplat | skipped:" in text, "no gsplat or no CUDA here: said, not hidden"
    # A run on the CPU: nothing to watch, and no claim about a GPU.
    assert json.loads((out / "3dgs" / training_table.NEIGHBOURS).read_text()) == {"device": "cpu"}
    assert "alone on its GPU" not in text and "not checked" not in text
    assert training_table.on_cpu(["--device=cpu"]) and training_table.on_cpu(["--x", "--device", "cpu"])
    assert not training_table.on_cpu(["--device=cuda"]) and not training_table.on_cpu([])
    # A finished run is read, not trained again.
    assert training_table.main([*argv, "--runs", "3dgs"]) == 0
    assert "3dgs: read the finished run" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        training_table.main([*argv, "--runs", "nonsense"])
    # A run with options of its own: its folder, its command line, its own seed over --seed. These
    # are options that a 20-iteration warm-up cannot take (a count to land on at a densification
    # step past it): the warm-up trains the base run, the timed run its own options.
    own = "3dgs@target-gaussians=260@densify-from=2@densify-every=4@densify-until=28@sh-every=5@seed=3"
    assert training_table.main([*argv, "--train-option=--device=cpu", "--iters", "30", "--runs", own]) == 0
    assert "the 20-iteration warm-up refused the run's own options; it warms up 3dgs" in capsys.readouterr().out
    folder = out / training_table.folder_name(own)
    assert folder.name == "3dgs_target-gaussians-260_densify-from-2_densify-every-4_densify-until-28_sh-every-5_seed-3"
    metrics = json.loads((folder / "metrics.json").read_text())
    assert (metrics["iterations"], metrics["num_gaussians"]) == (30, 260)
    config = json.loads((folder / "config.json").read_text())["train"]
    assert (config["sh_every"], config["seed"], config["strategy"]) == (5, 3, "3dgs")
    assert f"| {own} |" in docs.read_text()
    for bad in ("3dgs@=1", "3dgs@--seed=1", "3dgs@seed=", "nonsense@seed=1"):
        with pytest.raises(SystemExit):
            training_table.main([*argv, "--runs", bad])


def test_scaling_table_runs_each_config_and_writes_the_table_into_the_docs(tmp_path, capsys):
    import scaling_table

    scene = make_procedural_scene(tmp_path / "scene", views=6, width=32, height=24, points=200)
    docs = tmp_path / "dist.md"
    docs.write_text(f"# Dist\n\n{scaling_table.BEGIN}\nold\n{scaling_table.END}\nafter\n")
    out = tmp_path / "runs"
    argv = ["--data", str(scene), "--out", str(out), "--strategies", "3dgs", "--iters", "8", "--docs", str(docs)]
    argv += ["--device", "cpu", "--warmup", "0", "--configs", "1x1", "2x2", "--train-option=--dist-exchange=colours"]
    assert scaling_table.main(argv) == 0
    one, two = (json.loads((out / f"3dgs-{c}" / "metrics.json").read_text()) for c in ("1x1", "2x2"))
    assert (one["processes"], one["batch_size"], two["processes"], two["batch_size"]) == (1, 1, 2, 2)
    assert one["iterations"] == two["iterations"] == 8, "every config sees the same number of views"
    text = docs.read_text()
    assert "old" not in text and text.endswith("after\n")
    assert "(`python benchmarks/scaling_table.py --train-option=--dist-exchange=colours`)" in text, (
        "what the runs ran with"
    )
    assert json.loads((out / "3dgs-2x2" / "config.json").read_text())["train"]["dist_exchange"] == "colours"
    rows = [line for line in text.splitlines() if line.startswith("| 3dgs |")]
    assert rows[0].startswith("| 3dgs | 1 × 1 | 8 |") and "| 1.00× |" in rows[0]
    assert rows[1].startswith("| 3dgs | 2 × 2 | 4 |") and f"{two['num_gaussians']:,}" in rows[1]
    ratio = (8 / two["train_seconds"]) / (8 / one["train_seconds"])
    assert f"| {ratio:.2f}× |" in rows[1]
    capsys.readouterr()
    assert scaling_table.main(argv) == 0 and "read the finished run" in capsys.readouterr().out
    for bad in (["--configs", "2x1"], ["--configs", "two"], ["--strategies", "nonsense"]):
        with pytest.raises(SystemExit):
            scaling_table.main([*argv, *bad])
    # a finished run is read again only for a table of the options it was trained with
    other = [a for a in argv if a != "--train-option=--dist-exchange=colours"]
    with pytest.raises(SystemExit, match=r"3dgs-1x1 was trained with --train-option=--dist-exchange=colours"):
        scaling_table.main(other)
    assert text == docs.read_text(), "nothing written by the refused table"
    (out / "3dgs-1x1" / scaling_table.OPTIONS).write_text("{not json")
    with pytest.raises(SystemExit, match=r"train_options.json is not a record of --train-options"):
        scaling_table.main(argv)
    # one trained before runs recorded their options: read, and the table says so
    (out / "3dgs-1x1" / scaling_table.OPTIONS).unlink()
    assert scaling_table.main(argv) == 0
    assert "not checked against the heading's: 3dgs 1x1." in docs.read_text()


def test_a_run_past_its_limit_is_stopped_and_one_that_wrote_its_results_is_kept(tmp_path, monkeypatch, capsys):
    """--run-timeout: a launch that does not end is stopped with its whole process group; a timed
    run that had written its results (a 2-GPU run hung at exit once) is kept, marked ‡ with a note;
    one that had not stops the table with the reason."""
    import scaling_table
    import training_table

    start = time.monotonic()
    status, seen = training_table.run_watched(
        [sys.executable, "-c", "import time; time.sleep(60)"], [], every=0.1, limit=1.0
    )
    assert seen["stopped_after"] == 1.0 and status != 0 and time.monotonic() - start < 20

    scene = make_procedural_scene(tmp_path / "scene", views=6, width=32, height=24, points=200)
    out = tmp_path / "runs"
    argv = ["--data", str(scene), "--out", str(out), "--strategies", "3dgs", "--iters", "8", "--device", "cpu"]
    argv += ["--warmup", "0", "--configs", "1x1"]
    real = scaling_table.run_watched

    def hangs_after_its_results(line, gpus, **kwargs):  # the real run, then a process that does not end
        real(line, gpus, **kwargs)
        return real([sys.executable, "-c", "import time; time.sleep(60)"], gpus, every=0.1, limit=kwargs["limit"])

    monkeypatch.setattr(scaling_table, "run_watched", hangs_after_its_results)
    docs = tmp_path / "dist.md"
    docs.write_text(f"{scaling_table.BEGIN}\n{scaling_table.END}\n")
    assert scaling_table.main([*argv, "--run-timeout", "2", "--docs", str(docs)]) == 0
    assert "stopped after 2 s; it had written its results but not ended" in capsys.readouterr().out
    text = docs.read_text()
    assert "| 3dgs | 1 × 1 ‡ |" in text and "‡ stopped after 2 s" in text
    monkeypatch.setattr(
        scaling_table,
        "run_watched",
        lambda line, gpus, **kwargs: real(
            [sys.executable, "-c", "import time; time.sleep(60)"], gpus, every=0.1, limit=kwargs["limit"]
        ),
    )
    with pytest.raises(SystemExit, match="did not end within --run-timeout 1 s"):
        scaling_table.main([*argv, "--run-timeout", "1", "--retrain", "--out", str(tmp_path / "other")])
    with pytest.raises(SystemExit):
        scaling_table.main([*argv, "--run-timeout", "-1"])


def test_scaling_table_side_by_side_gives_each_one_gpu_run_a_gpu_of_its_own(tmp_path, monkeypatch):
    """Two stand-in GPUs (this machine's runs go to the CPU with --device auto): the one-GPU runs
    overlap in time, each seeing one of the parent's visible GPUs; the baseline then runs alone,
    and the 2-process run after it, on every GPU; the speed-ups are against the baseline alone."""
    import scaling_table

    scene = make_procedural_scene(tmp_path / "scene", views=6, width=32, height=24, points=200)
    calls, watched_gpus = [], {}
    real_watched = scaling_table.run_watched

    def recorded(line, gpus, **kwargs):  # the timed runs, each watched on its GPUs
        start = time.monotonic()
        status, seen = real_watched(line, gpus, **kwargs)
        out = line[line.index("--out") + 1]
        calls.append((out, kwargs["env"].get("CUDA_VISIBLE_DEVICES"), start, time.monotonic()))
        watched_gpus[os.path.basename(out)] = gpus
        return status, seen

    monkeypatch.setattr(scaling_table, "available_gpus", lambda: 2)
    monkeypatch.setattr(scaling_table, "run_watched", recorded)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "5,7")
    out = tmp_path / "runs"
    argv = ["--data", str(scene), "--out", str(out), "--strategies", "3dgs", "--iters", "6", "--device", "auto"]
    assert scaling_table.main([*argv, "--warmup", "0", "--configs", "1x1", "1x2", "2x2", "--side-by-side"]) == 0
    runs = {os.path.basename(folder): (gpu, start, end) for folder, gpu, start, end in calls}
    assert sorted(runs) == ["3dgs-1x1", "3dgs-1x1-alone", "3dgs-1x2", "3dgs-2x2"]
    (gpu_a, start_a, end_a), (gpu_b, start_b, end_b) = runs["3dgs-1x1"], runs["3dgs-1x2"]
    assert {gpu_a, gpu_b} == {"5", "7"}, "each one-GPU run sees one of the parent's GPUs"
    assert max(start_a, start_b) < min(end_a, end_b), "the one-GPU runs overlap in time"
    gpu_alone, start_alone, end_alone = runs["3dgs-1x1-alone"]
    gpu_c, start_c, _ = runs["3dgs-2x2"]
    assert gpu_alone == gpu_c == "5,7", "the baseline and the 2-process run see every GPU"
    assert watched_gpus == {"3dgs-1x1": [gpu_a], "3dgs-1x2": [gpu_b], "3dgs-1x1-alone": ["5"], "3dgs-2x2": ["5", "7"]}
    assert start_alone >= max(end_a, end_b) and start_c >= end_alone, "alone: after the others, one at a time"
    text = (out / "scaling.md").read_text()
    assert "side by side" in text and "| run |" in text
    rows = [line.split("|") for line in text.splitlines() if line.startswith("| 3dgs |")]
    assert [(r[2].strip(), r[3].strip()) for r in rows] == [
        ("1 × 1", "alone"),
        ("1 × 1", "side by side"),
        ("1 × 2", "side by side"),
        ("2 × 2", "alone"),
    ]
    alone = json.loads((out / "3dgs-1x1-alone" / "metrics.json").read_text())
    two = json.loads((out / "3dgs-2x2" / "metrics.json").read_text())
    ratio = (6 / two["train_seconds"]) / (6 / alone["train_seconds"])
    assert rows[0][7].strip() == "1.00×" and rows[3][7].strip() == f"{ratio:.2f}×"
    with pytest.raises(SystemExit):
        scaling_table.main([*argv[:-1], "cpu", "--side-by-side"])  # no GPUs to put the runs on


def test_scaling_table_takes_speed_ups_only_against_a_run_alone():
    """Side by side, a strategy whose baseline alone is missing (its first config skipped) gets no
    speed-up, not one against a run that shared the host; runs alone give the baseline."""
    import scaling_table

    args = argparse.Namespace(data="scene", images="images", iters=100, train_options=[])

    def run(seconds):
        return {"iterations": 100, "train_seconds": seconds, "num_gaussians": 10, "test": {}}

    rows = {
        ("a", "2x2", "alone"): {"skipped": "needs 2 GPUs"},
        ("a", "1x1", "side by side"): run(10.0),
        ("b", "1x1", "alone"): run(10.0),
        ("b", "1x1", "side by side"): run(12.5),
        ("b", "2x2", "alone"): run(6.25),
    }
    text = scaling_table.table(rows, "a machine", args, side_by_side=True)
    speedups = [line.split("|")[7].strip() for line in text.splitlines() if line.startswith(("| a | 1", "| b |"))]
    assert speedups == ["—", "1.00×", "0.80×", "1.60×"]
    assert "not checked for other processes on the GPU: a 1x1, b 1x1 alone, b 1x1, b 2x2" in text
    # What the watch saw of each run's GPUs: another process beside the 2-GPU run is said and marked.
    for key in rows:
        if "skipped" not in rows[key]:
            rows[key]["neighbours"] = {"most_others": 1 if key == ("b", "2x2", "alone") else 0}
    text = scaling_table.table(rows, "a machine", args, side_by_side=True)
    assert "b 2x2 shared the GPU with other processes (marked †): their times are not timings" in text
    assert "| b | 2 × 2 † | alone |" in text and "| b | 1 × 1 | alone |" in text and "not checked" not in text
    # A baseline that shared its GPU marks every speed-up taken against it.
    rows[("b", "1x1", "alone")]["neighbours"]["most_others"] = 1
    text = scaling_table.table(rows, "a machine", args, side_by_side=True)
    speedups = [line.split("|")[7].strip() for line in text.splitlines() if line.startswith(("| a | 1", "| b |"))]
    assert speedups == ["—", "1.00× †", "0.80× †", "1.60× †"]


def test_visible_share_by_hand(tmp_path, capsys):
    """Two cameras at the origin, one looking along +z and one along -z, 10 x 10 pixels, focal 10:
    which of four points each sees (in front, within the margin around the frame) worked out by hand."""
    import visible_share

    from cdcgs.io.views import View

    K = torch.tensor([[10.0, 0.0, 5.0], [0.0, 10.0, 5.0], [0.0, 0.0, 1.0]])
    back = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # a half turn about y: looks along -z
    views = [View("front", "", 10, 10, K, torch.eye(4)), View("back", "", 10, 10, K, back)]
    # (0,0,1): centre of the front view; (0,0,-1): centre of the back one; (2,0,1): u = 25, far
    # outside; (0.6,0,1): u = 11, outside the frame but inside a 15% margin (u < 11.5).
    points = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [2.0, 0.0, 1.0], [0.6, 0.0, 1.0]])
    masks = visible_share.visible_masks(points, views, margin=0.15)
    assert masks.tolist() == [[True, False, False, True], [False, True, False, False]]
    assert visible_share.visible_masks(points, views, margin=0.0)[0].tolist() == [True, False, False, False]
    generator = torch.Generator().manual_seed(0)
    assert visible_share.union_share(masks, 2, 5, generator) == 0.75  # both views: 3 of 4 points
    assert visible_share.union_share(masks, 1, 400, generator) == pytest.approx(0.375, abs=0.05)
    scene = make_procedural_scene(tmp_path / "scene", views=6, width=32, height=24, points=200)
    out = tmp_path / "share.json"
    assert visible_share.main(["--data", str(scene), "--batch", "2", "--samples", "50", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["per_view"]["min"] <= report["per_view"]["mean"] <= report["union"]["2"] <= 1.0
    assert "random views see" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        visible_share.main(["--data", str(scene), "--batch", "99"])


def test_process_poses_finds_the_view_that_moved(tmp_path, capsys):
    """A reference set of cameras and the same set carried into another frame by a similarity, one
    centre moved outward by half the spread: without the move everything agrees after the alignment,
    with it that view stands out and the steps to and from it are the breaks; with two trainings' per-view PSNR, the view that loses the most is listed with it."""
    import process_poses

    from cdcgs.geometry import quat_to_rotation

    g = torch.Generator().manual_seed(1)
    reference = {}
    for k in range(12):
        angle = 2 * math.pi * k / 12
        centre = torch.tensor([3 * math.cos(angle), 3 * math.sin(angle), 0.5], dtype=torch.float64)
        reference[f"v{k:02d}"] = (centre, quat_to_rotation(torch.randn(4, generator=g, dtype=torch.float64)))
    rotation = quat_to_rotation(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64))
    scale, shift = 0.4, torch.tensor([5.0, -1.0, 2.0], dtype=torch.float64)
    processed = {  # the reference frame is rotation @ (s x) + shift of the processed one
        name: (rotation.T @ (centre - shift) / scale, w2c @ rotation) for name, (centre, w2c) in reference.items()
    }
    exact = process_poses.compare(reference, processed)
    # 1e-4: the arccos of a rotation error near 0 loses about half the digits
    assert max(max(e) for e in exact.values()) < 1e-4, "centres and rotations agree up to the similarity"
    assert process_poses.breaks(reference, processed) == []
    turn = quat_to_rotation(torch.tensor([math.cos(0.05), 0.0, 0.0, math.sin(0.05)], dtype=torch.float64))
    turned = dict(processed, v07=(processed["v07"][0], turn @ processed["v07"][1]))  # turned by 0.1 rad
    assert process_poses.compare(reference, turned)["v07"][1] == pytest.approx(math.degrees(0.1), abs=0.01)
    spread = 3.0  # the reference centres' largest distance from their mean (a circle of radius 3)
    outward = reference["v03"][0] + torch.tensor([0.0, 0.5 * spread, 0.0], dtype=torch.float64)  # v03 is at +y
    processed["v03"] = (rotation.T @ (outward - shift) / scale, processed["v03"][1])
    errors = process_poses.compare(reference, processed)
    others = max(e[0] for n, e in errors.items() if n != "v03")  # least squares spreads a little of it
    assert errors["v03"][0] > 0.3 and errors["v03"][0] > 3 * others
    found = process_poses.breaks(reference, processed)
    assert [(a, b) for a, b, _, _ in found] == [("v02", "v03"), ("v03", "v04")], "the steps to and from v03"
    scene = make_procedural_scene(tmp_path / "scene", views=6, width=32, height=24, points=100)
    names = sorted(process_poses.poses(str(scene)))
    runs = []
    for k, psnr in enumerate(([30.0] * 6, [29.5] * 5 + [20.0])):
        run = tmp_path / f"run{k}"
        run.mkdir()
        per_view = [{"name": n, "psnr": p} for n, p in zip(names, psnr)]
        (run / "metrics.json").write_text(json.dumps({"per_view": per_view}))
        runs.append(str(run))
    assert process_poses.main(["--reference", str(scene), "--processed", str(scene), "--runs", *runs]) == 0
    out = capsys.readouterr().out
    assert "6 views in both models" in out and "median 0.00" in out
    assert f"| {names[-1]} | 30.00 | 20.00 | 10.00 | 0.0% |" in out, "the worst view first"
    assert "mean PSNR loss 2.08 dB" in out  # (5 x 0.5 + 10) / 6


def test_allreduce_times_the_exchange_of_each_count_on_two_processes(tmp_path):
    import allreduce

    out = tmp_path / "allreduce.json"
    script = os.path.join(os.path.dirname(allreduce.__file__), "allreduce.py")
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", script]
    command += ["--device", "cpu", "--gaussians", "300", "2001", "--repeats", "2", "--out", str(out)]
    environment = {k: v for k, v in os.environ.items() if not k.startswith("NCCL_")}
    environment["NCCL_DEBUG"] = "WARN"
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, env=environment)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.read_text())
    assert (report["processes"], report["backend"], [r["gaussians"] for r in report["rows"]]) == (
        2,
        "gloo",
        [300, 2001],
    )
    for row in report["rows"]:  # 59 gradients and 2 statistics per Gaussian, float32
        assert row["bytes"] == 4 * 61 * row["gaussians"]
        assert min(row["pack_ms"], row["all_reduce_ms"]) > 0 and row["exchange_ms"] >= 0
        assert row["all_reduce_gb_per_second"] == pytest.approx(row["bytes"] / row["all_reduce_ms"] / 1e6)
    # the shards' exchanges of rank 0 (slices of 150 / 150 and 1,001 / 1,000 Gaussians): 12 numbers
    # (48 bytes) of each of its own Gaussians forward, 10 floats (40 bytes) of each of the other's back
    bytes_sent = [(r["shards_forward_bytes"], r["shards_back_bytes"]) for r in report["rows"]]
    assert bytes_sent == [(7_200, 6_000), (48_048, 40_000)]
    for row in report["rows"]:
        for part in ("forward", "back"):
            assert row[f"shards_{part}_ms"] > 0
            rate = row[f"shards_{part}_bytes"] / row[f"shards_{part}_ms"] / 1e6
            assert row[f"shards_{part}_gb_per_second"] == pytest.approx(rate)
    assert report["nccl_env"] == {"NCCL_DEBUG": "WARN"}, "the launch's NCCL variables, recorded"
    assert report["nccl_version"] is None  # gloo on the CPU
    assert "NCCL (not used): NCCL_DEBUG=WARN" in done.stdout
    assert done.stdout.count("| 2,001 |") == 1, "rank 0 alone prints the table"
    with pytest.raises(SystemExit):
        allreduce.main(["--device", "cpu"])  # one process: refused
    with pytest.raises(SystemExit):
        allreduce.main(["--device", "cpu", "--gaussians", "0"])


def test_eval_memory_measures_every_setting_and_its_own_process_gets_its_variable(tmp_path, capsys):
    import eval_memory

    scene = make_procedural_scene(tmp_path / "scene", views=16, width=48, height=36, points=300)
    out = tmp_path / "eval_memory.json"
    argv = ["--device", "cpu", "--data", str(scene), "--weights", "random", "--repeats", "1"]
    eval_memory.main([*argv, "--settings", "native", "cudnn", "wscap", "--wscap", "64", "--out", str(out)])
    report = json.loads(out.read_text())
    rows = report["rows"]
    parts = ["lpips_vgg", "lpips_alex", "ssim", "psnr"]
    assert [(r["setting"], r["part"]) for r in rows] == [(s, p) for s in ("wscap", "native", "cudnn") for p in parts]
    assert all(r["environment"] == {"CUDNN_CONV_WSCAP_DBG": "64"} for r in rows if r["setting"] == "wscap")
    assert all(r[key] is None for r in rows for key in eval_memory.MEMORY_KEYS), "no GPU memory on the CPU"
    assert all(r["first_s"] > 0 and r["then_s"] >= 0 for r in rows)
    # On the CPU every setting is the same computation, in this process or its own (to float
    # rounding: a process of its own may split the convolutions over another number of threads).
    assert all(r["max_abs_diff"] <= 1e-6 for r in rows)
    # The scores are those of the two test views: PSNR by numpy, LPIPS by the module one pair at a time.
    args = argparse.Namespace(data=str(scene), factor=None, images=2, seed=0)
    images, targets, _ = eval_memory.image_pairs(args, torch.device("cpu"))
    assert len(images) == 2
    by_part = {r["part"]: r["scores"] for r in rows if r["setting"] == "native"}
    expected_psnr = [-10 * np.log10(np.mean((x.numpy() - y.numpy()) ** 2)) for x, y in zip(images, targets)]
    assert by_part["psnr"] == pytest.approx(expected_psnr, abs=1e-4)
    for name in ("vgg", "alex"):
        net = eval_memory.random_lpips(name, seed=0)
        with torch.no_grad():
            direct = [net(x.permute(2, 0, 1)[None], y.permute(2, 0, 1)[None]).item() for x, y in zip(images, targets)]
        assert by_part[f"lpips_{name}"] == pytest.approx(direct, rel=1e-5)
        assert all(score > 0 for score in direct)
    assert all(-1 <= score <= 1 for score in by_part["ssim"])
    printed = capsys.readouterr().out
    assert "max|d|" in printed and "CUDNN_CONV_WSCAP_DBG=64" in printed


def test_bench_rasterize_times_the_render_without_its_count_read(tmp_path, capsys):
    import bench_rasterize

    workload = tmp_path / "workload.py"
    workload.write_text(WORKLOAD)
    argv = ["--sizes", "60", "--device", "cpu", "--warmup", "1", "--iters", "2", "--workload", str(workload)]
    rows = bench_rasterize.main([*argv, "--capacity", "1", "2.5", "--out", str(tmp_path / "r.json")])
    names = [r["renderer"] for r in rows if "forward_ms" in r]
    assert names[:3] == ["cdcgs", "cdcgs capacity 1x", "cdcgs capacity 2.5x"], names
    assert all(r["pipelined_ms"] > 0 and r["intersections"] == rows[0]["intersections"] > 0 for r in rows[:3])
    assert "| fwd+bwd pipelined ms |" in capsys.readouterr().out
    with pytest.raises(SystemExit):  # a margin below 1 has no room for every pair
        bench_rasterize.main([*argv, "--capacity", "0.5"])
    assert "margins must be at least 1" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="with a GPU the script measures instead")
def test_tile_balance_schedules_the_walks_by_hand_and_runs_on_a_scene(tmp_path, capsys):
    """Jobs of 9, 1, 1, 1 (+ 0 overhead) on two slots: in order the 9 starts at once (makespan 9);
    longest first the same; 1, 1, 9 in order ends at 10, longest first at 9. Then the script on a
    small scene (no order ends before the longest walk, split walks sooner still), and the walks
    against a loop over the pixels."""
    import tile_balance

    assert tile_balance.makespan([9.0, 1.0, 1.0, 1.0], 2, [0, 1, 2, 3]) == 9.0
    assert tile_balance.makespan([1.0, 1.0, 9.0], 2, [0, 1, 2]) == 10.0
    lengths = torch.tensor([1, 1, 9])
    report = tile_balance.balance(lengths, lengths, 2, 0.0)
    assert (report["numbered"], report["longest_first"], report["any_order"], report["split"]) == (10.0, 9.0, 9.0, 5.5)
    # chunks of 4: the 9 as 4, 4, 1 beside the two 1s; on two slots 1 + 4 + 1 and 1 + 4, so 6
    assert tile_balance.chunked_costs([1, 1, 9, 0], 4, 0.0) == [1.0, 1.0, 4.0, 4.0, 1.0]
    assert tile_balance.balance(lengths, lengths, 2, 0.0, (4,))["chunked"] == {"4": 6.0}
    scene = make_procedural_scene(tmp_path / "scene", views=6, width=48, height=36, points=300)
    out = tmp_path / "balance.json"
    assert tile_balance.main(["--data", str(scene), "--gaussians", "800", "--views", "0", "1", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [row["view"] for row in rows] == [0, 1] and all(row["gaussians"] == 800 for row in rows)
    for row in rows:
        assert row["walk_max"] > 0 and row["split"] <= row["any_order"] <= min(row["numbered"], row["longest_first"])
    assert "longest first" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        tile_balance.main(["--data", str(scene), "--views", "99"])
    # The walks against a loop over the tiles' pixels.
    from conftest import make_scene

    import cdcgs

    small = make_scene(300, 40, 24, sh_degree=0, seed=3)
    _, _, info = cdcgs.rasterize(*small.tensors(), viewmat=small.viewmat, K=small.K, width=40, height=24)
    lengths, walks = tile_balance.tile_walks(info)
    for tile in range(info.tiles_x * info.tiles_y):
        ty, tx = divmod(tile, info.tiles_x)
        start, end = info.tile_ranges[tile].tolist()
        last = info.last_contributor[ty * 16 : ty * 16 + 16, tx * 16 : tx * 16 + 16].max().item()
        assert lengths[tile] == end - start
        assert walks[tile] == (max(last - start + 1, 0) if end > start else 0) and walks[tile] <= lengths[tile]
    assert walks.max() > 0


def test_graph_step_says_it_needs_a_gpu():
    import graph_step

    with pytest.raises(SystemExit, match="needs a CUDA GPU"):
        graph_step.main(["--data", "unused"])


def test_time_split_adds_the_spans_by_hand(tmp_path, capsys):
    """history.json's train_seconds at steps 50..300 (every 50): spans to 100, 200 and the last
    step (300); --at 1000 is past the run and 150 not a span's end unless asked. Then a folder
    without a history is refused by name."""
    import time_split

    run = tmp_path / "run"
    run.mkdir()
    steps = [50, 100, 150, 200, 250, 300]
    seconds = [0.5, 0.7, 1.0, 1.4, 1.5, 1.6]
    history = {
        "step": steps,
        "gaussians": [10, 20, 30, 40, 40, 40],
        "train_seconds": [{"step": s, "seconds": t} for s, t in zip(steps, seconds)],
    }
    (run / "history.json").write_text(json.dumps(history))
    metrics = {
        "train_seconds": 1.6,
        "refine_seconds": 0.3,
        "gamma_seconds": 0.0,
        "cuda_graph": {"capture_seconds": 0.1, "capture_wait_seconds": 0.25},
    }
    (run / "metrics.json").write_text(json.dumps(metrics))
    out = tmp_path / "split.json"
    assert time_split.main([str(run), "--at", "100", "200", "1000", "--out", str(out)]) == 0
    spans = json.loads(out.read_text())[0]["spans"]
    assert [(s["from"], s["to"], s["gaussians"]) for s in spans] == [(0, 100, 20), (100, 200, 40), (200, 300, 40)]
    assert [s["seconds"] for s in spans] == pytest.approx([0.7, 0.7, 0.2])
    assert [s["ms_per_iteration"] for s in spans] == pytest.approx([7.0, 7.0, 2.0])
    printed = capsys.readouterr().out
    assert "| 100–200 | 0.7 s (7.00 ms, 0.00M) |" in printed and "| captures | 0.1 s |" in printed
    assert "| waits before captures | 0.2 s |" in printed
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        time_split.main([str(tmp_path / "empty")])
    assert "has no history.json" in capsys.readouterr().err


def test_the_tables_name_the_commit_and_say_when_the_tree_differs(tmp_path, monkeypatch):
    """training_table.commit() (the scaling table's too): HEAD's short hash in a clean tree; with a
    tracked file changed, the hash and "+ uncommitted changes"; outside a repository, "unknown"."""
    import training_table

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "a.txt").write_text("one\n")
    git("add", "a.txt")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "first")
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=tmp_path, capture_output=True, text=True
    ).stdout.strip()
    monkeypatch.setattr(training_table, "ROOT", str(tmp_path))
    (tmp_path / "new.txt").write_text("untracked files do not count\n")
    assert training_table.commit() == head
    (tmp_path / "a.txt").write_text("two\n")
    assert training_table.commit() == f"{head} + uncommitted changes"
    outside = tmp_path / "outside"
    outside.mkdir()
    monkeypatch.setattr(training_table, "ROOT", str(outside))
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path))
    assert training_table.commit() == "unknown"


def test_shard_step_times_the_three_ways_on_two_processes(tiny_scene, tmp_path):
    import shard_step

    out = tmp_path / "shard_step.json"
    script = os.path.join(os.path.dirname(shard_step.__file__), "shard_step.py")
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", script]
    command += ["--data", str(tiny_scene), "--device", "cpu", "--gaussians", "301", "--repeats", "1", "--out", str(out)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(out.read_text())
    assert (report["processes"], report["backend"], report["size"]) == (2, "gloo", "48 x 36")
    (row,) = report["rows"]
    assert (row["gaussians"], row["slices"]) == (301, [151, 150])
    assert min(row[f"{way}_ms"] for way in shard_step.WAYS) > 0
    assert row["views_alone_ms"] >= row["one_view_ms"]  # the sum of both processes' own views
    for way in shard_step.WAYS[1:]:
        assert row[f"{way}_speedup"] == pytest.approx(row["views_alone_ms"] / row[f"{way}_ms"])
    assert done.stdout.count("| 301 |") == 1, "rank 0 alone prints the table"
    assert shard_step.slices(10, 3) == [4, 3, 3]
    with pytest.raises(SystemExit):
        shard_step.main(["--data", str(tiny_scene), "--device", "cpu"])  # one process: refused
    with pytest.raises(SystemExit):
        shard_step.main(["--data", str(tiny_scene), "--gaussians", "0"])


def test_profile_training_profiles_a_window_of_a_real_training(tmp_path, capsys, monkeypatch):
    """A window of two optimizer steps from iteration 3 of an 8-iteration training on the CPU: the
    training runs as cdcgs train runs it (its files written), the window holds steps 4 and 5, and the
    report has this process's figures; a window past the training's end says that nothing was
    profiled; the benchmark's own options are checked."""
    import profile_training

    scene = make_procedural_scene(tmp_path / "scene", views=6, width=32, height=24, points=200)
    out = tmp_path / "profile.json"
    train = ["--data", str(scene), "--iters", "8", "--device", "cpu", "--out", str(tmp_path / "run")]
    train += ["--eval-every", "0", "--no-save-renders", "--no-progress"]
    assert profile_training.main(["--from", "3", "--steps", "2", "--out", str(out), "--", *train]) == 0
    assert (tmp_path / "run" / "metrics.json").is_file()
    report = json.loads(out.read_text())
    assert report["train_options"] == train
    (mine,) = report["ranks"]
    assert (mine["rank"], mine["steps"], mine["iterations"], mine["device"]) == (0, 2, [4, 5], "cpu")
    assert mine["rewinds"] == 0
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert mine["gaussians"] == metrics["num_gaussians"] and mine["wall_ms_per_step"] > 0
    assert "| wall (ms, profiled) |" in capsys.readouterr().out
    # a scene that is not there: cdcgs train's error, named, no traceback
    missing = ["--data", str(tmp_path / "nowhere"), "--device", "cpu", "--out", str(tmp_path / "none")]
    assert profile_training.main(["--", *missing]) == 2
    assert "nowhere" in capsys.readouterr().err
    # a training that ends before the window (its callback never called: no steps at all)
    monkeypatch.setattr(profile_training.cli, "cmd_train", lambda args, callbacks=(): 0)
    assert profile_training.main(["--from", "10", "--", *train]) == 1
    assert "ended before iteration 10" in capsys.readouterr().err
    for bad in (["--steps", "0", "--", *train], ["--from", "2"]):
        with pytest.raises(SystemExit):
            profile_training.main(bad)
