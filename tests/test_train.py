"""Training end to end on a tiny procedural scene (CPU): quality rises, outputs, resume, CLI."""

import json
import os
import subprocess
import sys

import pytest
import torch
from helpers import DEFAULT_DEVICE, SHORT, interrupt_at, tiny_config, train_argv, warp_without_ordinals

from cdcgs.cli import main as cli_main
from cdcgs.errors import InputError
from cdcgs.io import load_checkpoint, read_ply
from cdcgs.train.evaluate import lpips_metric
from cdcgs.train.trainer import Trainer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LPIPS_AVAILABLE = not lpips_metric("cpu").note


def test_without_lpips_weights_evaluation_reports_null_and_how_to_get_them(tiny_scene, tmp_path, monkeypatch, capsys):
    from cdcgs.lpips import weights as lpips_weights

    monkeypatch.setenv("CDCGS_CACHE", str(tmp_path / "empty-cache"))
    monkeypatch.setattr(lpips_weights, "_torchvision_state", lambda net: None)
    argv = ["train", "--data", str(tiny_scene), "--out", str(tmp_path / "run"), "--iters", "5", "--no-progress"]
    assert cli_main([*argv, "--device", DEFAULT_DEVICE]) == 0
    printed = capsys.readouterr().out
    assert printed.count("run `cdcgs weights lpips` once") == 1 and "LPIPS-VGG" not in printed
    test = json.load(open(tmp_path / "run" / "metrics.json"))["test"]
    assert test["lpips_vgg"] is None and test["lpips_alex"] is None
    assert "LPIPS-vgg" in test["lpips_note"] and "LPIPS-alex" in test["lpips_note"]


def test_training_improves_held_out_psnr_and_writes_outputs(tiny_scene, tmp_path, device):
    initial = Trainer(tiny_config(tiny_scene, tmp_path / "zero", device, iters=1), SHORT).run()["test"]["psnr"]
    result = Trainer(tiny_config(tiny_scene, tmp_path / "run", device, iters=250, eval_every=100), SHORT).run()
    # Measured on this scene (CPU, seeds 0-12): about 19 dB after one step, 23.6-26.2 dB after 250
    # (mean 24.9; the split's random offsets alone move it by a dB).
    assert result["test"]["psnr"] > 23.0 and result["test"]["psnr"] > initial + 4.0
    assert result["num_gaussians"] > 1500, "densification must have added Gaussians"
    out = tmp_path / "run"
    names = sorted(os.listdir(out))
    for expected in (
        "checkpoint.pt",
        "config.json",
        "curves.png",
        "history.json",
        "metrics.json",
        "point_cloud.ply",
        "test_renders",
        "test_views.txt",
    ):
        assert expected in names
    metrics = json.load(open(out / "metrics.json"))
    for key in ("lpips_vgg", "lpips_alex"):
        if LPIPS_AVAILABLE:  # the mean of the per-view scores, each a real number
            per_view = [entry[key] for entry in metrics["per_view"]]
            assert metrics["test"][key] == pytest.approx(sum(per_view) / len(per_view)) and min(per_view) > 0
        else:
            assert metrics["test"][key] is None and "cdcgs weights lpips" in metrics["test"]["lpips_note"]
    assert metrics["iterations"] == 250 and metrics["test"]["views"] == 2 and metrics["test"]["render_fps"] > 0
    assert len(os.listdir(out / "test_renders")) == 2
    history = json.load(open(out / "history.json"))
    assert [e["step"] for e in history["eval"]] == [100, 200, 250]
    seconds = [e["seconds"] for e in history["train_seconds"]]  # the training time at each log point
    assert [e["step"] for e in history["train_seconds"]] == history["step"]
    assert seconds[0] > 0 and seconds == sorted(seconds) and seconds[-1] == metrics["train_seconds"]
    assert read_ply(out / "point_cloud.ply").means.shape[0] == metrics["num_gaussians"]
    held = ("peak_gpu_memory_reserved_gb", "warp_mempool_peak_gb", "gpu_memory_in_use_gb")
    if device == "cuda":  # the caching allocator holds at least what was allocated; the device more still
        reserved, pool, in_use = (metrics[key] for key in held)
        assert reserved >= metrics["peak_gpu_memory_gb"] > 0 and pool >= 0 and in_use > metrics["peak_gpu_memory_gb"]
    else:
        assert [metrics[key] for key in held] == [None, None, None]
    assert metrics["held_gpu_memory_per_process"] == [{key: metrics[key] for key in held}]
    timeline = ("gpu_memory_reserved_gb", "gpu_memory_allocated_gb")
    if device == "cuda":  # the allocator at every log point and after every evaluation
        assert [e["step"] for e in history["gpu_memory"]] == history["step"]
        for entry in history["gpu_memory"] + history["eval"]:
            assert entry["gpu_memory_reserved_gb"] >= entry["gpu_memory_allocated_gb"] > 0
        assert max(e["gpu_memory_reserved_gb"] for e in history["gpu_memory"]) <= reserved
    else:
        assert "gpu_memory" not in history and not any(key in e for e in history["eval"] for key in timeline)


def test_held_memory_asks_warp_for_an_indexed_device(monkeypatch):
    """`--device cuda` (and auto) gives torch.device("cuda") without an index, which Warp's
    device_from_torch cannot look up: held_memory passes the current ordinal. Stand-ins for the
    CUDA and Warp calls, so this runs on the CPU."""
    import warp as wp

    from cdcgs.train.trainer import held_memory

    asked = warp_without_ordinals(monkeypatch, 1)
    monkeypatch.setattr(wp, "is_mempool_enabled", lambda device: True)
    monkeypatch.setattr(wp, "get_mempool_used_mem_high", lambda device: 3_000_000_000)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device: (70_000_000_000, 80_000_000_000))
    held = held_memory(torch.device("cuda"), 5_000_000_000)
    assert asked == [torch.device("cuda", 1)]
    assert held == {"peak_gpu_memory_reserved_gb": 5.0, "warp_mempool_peak_gb": 3.0, "gpu_memory_in_use_gb": 10.0}
    held_memory(torch.device("cuda", 0), 0)
    assert asked[-1] == torch.device("cuda", 0)


def test_allocator_now_reads_torchs_counters_on_cuda_only(monkeypatch):
    """Stand-ins for torch's CUDA counters, so this runs on the CPU: bytes become GB, and the CPU
    gives nothing (the history then has no memory timeline)."""
    from cdcgs.train.trainer import allocator_now

    asked = []
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda device: asked.append(device) or 7_500_000_000)
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device: asked.append(device) or 2_250_000_000)
    assert allocator_now(torch.device("cpu")) == {} and asked == []
    now = allocator_now(torch.device("cuda", 1))
    assert now == {"gpu_memory_reserved_gb": 7.5, "gpu_memory_allocated_gb": 2.25}
    assert asked == [torch.device("cuda", 1)] * 2


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="expandable segments exist on Linux only")
def test_the_command_line_asks_torch_for_expandable_segments_unless_told_otherwise():
    """Set before anything allocates on CUDA, in every command's process (and so its torchrun
    workers); a value the user set stays."""
    probe = "import os; from cdcgs.cli import main; main(['weights', '--help']); print(os.environ.get('PYTORCH_CUDA_ALLOC_CONF'))"

    def setting(**env):
        environment = {k: v for k, v in os.environ.items() if "ALLOC_CONF" not in k} | env
        done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, env=environment, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip().splitlines()[-1]

    assert setting() == "expandable_segments:True"
    assert setting(PYTORCH_CUDA_ALLOC_CONF="expandable_segments:False") == "expandable_segments:False"
    assert setting(PYTORCH_ALLOC_CONF="expandable_segments:False") == "None"  # torch >= 2.9's name counts too
    # The benchmarks set it the same way for the processes they start (gsplat's runs included).
    from cdcgs.cli import ask_for_expandable_segments

    children = {"PATH": "/bin"}
    ask_for_expandable_segments(children)
    assert children == {"PATH": "/bin", "PYTORCH_CUDA_ALLOC_CONF": "expandable_segments:True"}
    chosen = {"PYTORCH_ALLOC_CONF": "backend:cudaMallocAsync"}
    ask_for_expandable_segments(chosen)
    assert chosen == {"PYTORCH_ALLOC_CONF": "backend:cudaMallocAsync"}


def test_an_existing_run_is_not_overwritten(tiny_scene, tmp_path, capsys):
    Trainer(tiny_config(tiny_scene, tmp_path, iters=5), SHORT).run()
    before = (tmp_path / "checkpoint.pt").read_bytes()
    with pytest.raises(InputError, match=r"already holds a cdcgs run .*--resume.*--overwrite"):
        Trainer(tiny_config(tiny_scene, tmp_path, iters=5), SHORT).run()
    assert (tmp_path / "checkpoint.pt").read_bytes() == before
    argv = train_argv(tiny_scene, tmp_path, 5)
    assert cli_main(argv) == 2 and "already holds a cdcgs run" in capsys.readouterr().err
    assert cli_main([*argv, "--overwrite"]) == 0


def test_sh_degree_schedule(tiny_scene, tmp_path):
    trainer = Trainer(tiny_config(tiny_scene, tmp_path, iters=25, sh_every=10), SHORT)
    trainer._setup()
    degrees = []
    for _ in range(25):
        trainer.train_step()
        degrees.append(trainer.model.sh_degree)
    assert degrees[8] == 0 and degrees[9] == 1 and degrees[19] == 2 and degrees[24] == 2


@pytest.mark.skipif(
    DEFAULT_DEVICE != "cpu", reason="bitwise repeatable on the CPU only: on CUDA the order of float atomic adds varies"
)
def test_same_seed_same_run_and_resume_continues_it(tiny_scene, tmp_path, monkeypatch):
    straight = Trainer(tiny_config(tiny_scene, tmp_path / "a", iters=50, background="random"), SHORT)
    straight.run()
    again = Trainer(tiny_config(tiny_scene, tmp_path / "b", iters=50, background="random"), SHORT)
    again.run()
    # The same run, stopped by Ctrl-C at iteration 30 (mid-schedule, after densification steps).
    with monkeypatch.context() as patch:
        interrupt_at(patch, 30)
        with pytest.raises(KeyboardInterrupt):
            Trainer(tiny_config(tiny_scene, tmp_path / "c", iters=50, background="random"), SHORT).run()
    resumed = Trainer(tiny_config(tiny_scene, tmp_path / "c", iters=50, background="random", resume=True), SHORT)
    resumed.run()
    for name, p in straight.model.params.items():
        assert torch.equal(p, again.model.params[name]), f"{name}: same seed, different run"
        assert torch.equal(p, resumed.model.params[name]), f"{name}: the resumed run differs"


def test_ctrl_c_writes_checkpoint_and_ply(tiny_scene, tmp_path, monkeypatch):
    trainer = Trainer(tiny_config(tiny_scene, tmp_path), SHORT)
    interrupt_at(monkeypatch, 15)
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 15
    assert os.path.isfile(tmp_path / "point_cloud.ply")


def test_cli_train_eval_render_export(tiny_scene, tmp_path, capsys, device):
    out = tmp_path / "cli"
    code = cli_main(
        [
            "train",
            "--data",
            str(tiny_scene),
            "--out",
            str(out),
            "--iters",
            "30",
            "--device",
            device,
            "--no-progress",
            "--eval-every",
            "0",
            "--densify-from",
            "10",
            "--densify-every",
            "10",
            "--max-gaussians",
            "2000",
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "test: PSNR" in text and f"outputs in {out}" in text
    assert json.load(open(out / "config.json"))["strategy"]["max_gaussians"] == 2000
    assert cli_main(["eval", str(out), "--device", device]) == 0
    assert "test: PSNR" in capsys.readouterr().out
    # The same model as a bare PLY with its scene: the same scores, written beside nothing of the run.
    ply_eval = tmp_path / "ply_eval"
    assert (
        cli_main(
            [
                "eval",
                str(out / "point_cloud.ply"),
                "--data",
                str(tiny_scene),
                "--device",
                device,
                "--out",
                str(ply_eval),
            ]
        )
        == 0
    )
    from_run = json.load(open(out / "metrics.json"))["test"]
    from_ply = json.load(open(ply_eval / "metrics.json"))["test"]
    for key in ("psnr", "ssim", "lpips_vgg", "lpips_alex"):
        assert from_ply[key] == pytest.approx(from_run[key], rel=1e-5), key
    assert len(os.listdir(ply_eval / "test_renders")) == from_run["views"]
    # The run lists its test views; naming them holds out the same views whatever --test-every says.
    names = (out / "test_views.txt").read_text().split()
    assert names == [v["name"] for v in json.load(open(out / "metrics.json"))["per_view"]] and len(names) == 2
    named = tmp_path / "named_eval"
    args = ["eval", str(out / "point_cloud.ply"), "--data", str(tiny_scene), "--device", device, "--out", str(named)]
    assert cli_main([*args, "--test-every", "5", "--test-views", str(out / "test_views.txt")]) == 0
    named_metrics = json.load(open(named / "metrics.json"))
    assert [v["name"] for v in named_metrics["per_view"]] == names
    assert named_metrics["test"]["psnr"] == pytest.approx(from_run["psnr"], rel=1e-5)
    assert cli_main(["eval", str(out), "--test-views", str(out / "test_views.txt"), "--device", device]) == 2
    assert "--test-views is for evaluating a PLY" in capsys.readouterr().err
    assert cli_main(["eval", str(out / "point_cloud.ply"), "--device", device]) == 2
    assert "needs its scene: --data DIR" in capsys.readouterr().err
    assert cli_main(["eval", str(out), "--data", str(tiny_scene), "--device", device]) == 2
    assert "--data is for evaluating a PLY" in capsys.readouterr().err
    assert cli_main(["render", str(out), "--device", device]) == 0
    assert len(os.listdir(out / "renders_test")) == 2
    assert cli_main(["render", str(out), "--path", "orbit", "--frames", "6", "--device", device]) == 0
    assert len(os.listdir(out / "renders_orbit")) == 6
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:  # the GPU image lacks it: the CLI must say so
        assert cli_main(["render", str(out), "--video", str(tmp_path / "orbit.mp4")]) == 2
        assert "needs the imageio-ffmpeg package" in capsys.readouterr().err
    else:
        assert (
            cli_main(
                [
                    "render",
                    str(out),
                    "--path",
                    "orbit",
                    "--frames",
                    "6",
                    "--video",
                    str(tmp_path / "orbit.mp4"),
                    "--device",
                    device,
                ]
            )
            == 0
        )
        assert (tmp_path / "orbit.mp4").stat().st_size > 1000
    assert cli_main(["export", str(out), str(tmp_path / "model.ply")]) == 0
    assert read_ply(tmp_path / "model.ply").means.shape[0] == read_ply(out / "point_cloud.ply").means.shape[0]


def test_named_test_views_are_held_out_kept_on_resume_and_read_back(tiny_scene, tmp_path, capsys):
    from cdcgs.io import load_scene
    from cdcgs.train.outputs import load_run

    names = [v.name for v in load_scene(tiny_scene, test_every=0, load_images_now=False, progress=False).train]
    chosen = [names[6], names[1], names[5]]  # not every 8th: index 0 and 8 would be
    listed = tmp_path / "names.txt"
    listed.write_text("\n".join(chosen) + "\n")
    out = tmp_path / "run"
    assert cli_main(train_argv(tiny_scene, out, 6, "--test-views", str(listed))) == 0
    assert (out / "test_views.txt").read_text().split() == sorted(chosen)
    assert [v["name"] for v in json.load(open(out / "metrics.json"))["per_view"]] == sorted(chosen)
    # Resuming with another split (here every 8th, the default) would train on held-out views.
    assert cli_main(train_argv(tiny_scene, out, 9, "--resume")) == 2
    err = capsys.readouterr().err
    assert "held out 3 test view(s)" in err and str(out / "test_views.txt") in err, err
    assert cli_main(train_argv(tiny_scene, out, 9, "--resume", "--test-views", str(out / "test_views.txt"))) == 0
    assert json.load(open(out / "metrics.json"))["iterations"] == 9
    # A finished run holds out the names it recorded, wherever the file it was given went.
    listed.unlink()
    assert [v.name for v in load_run(out).load_scene(load_images=False).test] == sorted(chosen)


@pytest.mark.parametrize(
    "argv,message",
    [
        (["train", "--data", "/nonexistent/scene"], "no such scene folder"),
        (["train", "--data", "{scene}", "--grad-threshold", "1e-4", "--strategy", "nope"], "invalid choice: 'nope'"),
        (["train", "--data", "{scene}", "--device", "tpu"], "device 'tpu'"),
        (["train", "--data", "{scene}", "--background", "green"], "invalid choice: 'green'"),
        (["eval", "/nonexistent/out"], "no such run folder"),
        (["export", "/nonexistent/out", "x.ply"], "no such output folder"),
    ],
)
def test_cli_bad_input(tiny_scene, tmp_path, capsys, argv, message):
    argv = [a.replace("{scene}", str(tiny_scene)) for a in argv] + (
        ["--out", str(tmp_path / "o"), "--no-progress", "--device", DEFAULT_DEVICE]
        if argv[0] == "train" and "--device" not in argv
        else []
    )
    assert cli_main(argv) == 2
    assert message in capsys.readouterr().err


def test_cli_help_lists_every_option():
    result = subprocess.run(
        [sys.executable, "-m", "cdcgs", "train", "--help"], capture_output=True, text=True, cwd=ROOT
    )
    assert result.returncode == 0
    for flag in (
        "--data",
        "--images",
        "--strategy",
        "--iters",
        "--device",
        "--out",
        "--resume",
        "--lr-means-init",
        "--max-gaussians",
        "--absgrad",
    ):
        assert flag in result.stdout


def write_lock(folder, pid, host=None):
    import socket

    folder.mkdir(parents=True, exist_ok=True)
    holder = {"pid": pid, "host": host or socket.gethostname(), "started": "2026-11-23 10:00:00"}
    (folder / ".lock").write_text(json.dumps(holder))


def test_a_run_folder_in_use_is_refused_even_with_overwrite(tiny_scene, tmp_path, capsys):
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        out = tmp_path / "busy"
        write_lock(out, holder.pid)
        for extra in ([], ["--overwrite"], ["--resume"]):
            argv = ["train", "--data", str(tiny_scene), "--out", str(out), "--iters", "5", "--no-progress", *extra]
            assert cli_main([*argv, "--device", DEFAULT_DEVICE]) == 2
            err = capsys.readouterr().err
            assert f"in use by another training (pid {holder.pid} on " in err, err
        assert sorted(os.listdir(out)) == [".lock"], "nothing written beside the holder's lock"
    finally:
        holder.kill()
        holder.wait()


def test_a_lock_from_another_machine_is_refused_and_a_dead_ones_taken_over(tiny_scene, tmp_path, capsys, caplog):
    out = tmp_path / "run"
    write_lock(out, 12345, host="some-other-machine")
    argv = train_argv(tiny_scene, out, 5)
    assert cli_main(argv) == 2
    assert "another machine's cannot be checked from here), delete" in capsys.readouterr().err
    finished = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    write_lock(out, int(finished.stdout))  # a process of this machine that is gone
    assert cli_main(argv) == 0
    assert f"took over the lock of a training that is gone (pid {int(finished.stdout)}" in caplog.text
    assert not (out / ".lock").exists() and (out / "metrics.json").exists()
    write_lock(out, 12345, host="some-other-machine")  # eval does not write into a busy run either
    assert cli_main(["eval", str(out), "--device", DEFAULT_DEVICE]) == 2
    assert "in use by another training" in capsys.readouterr().err


def test_bad_out_paths_and_failed_runs_leave_nothing_behind(tiny_scene, tmp_path, capsys):
    a_file = tmp_path / "file.txt"
    a_file.write_text("keep me")
    base = ["train", "--iters", "5", "--no-progress", "--device", DEFAULT_DEVICE]
    assert cli_main([*base, "--data", str(tiny_scene), "--out", str(a_file)]) == 2
    assert "--out names a file, not a folder" in capsys.readouterr().err and a_file.read_text() == "keep me"
    assert cli_main([*base, "--data", str(tmp_path / "no-scene"), "--out", str(tmp_path / "new")]) == 2
    assert "no such scene folder" in capsys.readouterr().err
    assert not (tmp_path / "new").exists(), "a failed run leaves no empty folder"


def test_the_lock_is_released_after_an_interrupt(tiny_scene, tmp_path, monkeypatch):
    interrupt_at(monkeypatch, 7)
    with pytest.raises(KeyboardInterrupt):
        Trainer(tiny_config(tiny_scene, tmp_path, iters=20)).run()
    assert (tmp_path / "checkpoint.pt").exists() and not (tmp_path / ".lock").exists()


@pytest.mark.parametrize(
    "option,value,message",
    [
        ("--grad-threshold", "nan", "--grad-threshold must be a finite number, got nan"),
        ("--grad-threshold", "-1", "--grad-threshold must be in [0.0, inf], got -1.0"),
        ("--lr-means-init", "-0.0001", "--lr-means-init must be in (0.0, inf], got -0.0001"),
        ("--lr-opacity-logits", "inf", "--lr-opacity-logits must be a finite number, got inf"),
        ("--reset-value", "2", "--reset-value must be in (0.0, 1.0], got 2.0"),
        ("--rho-densify", "1.5", "--rho-densify must be in [0.0, 1.0], got 1.5"),
        ("--densify-every", "0", "--densify-every must be in [1, inf], got 0"),
        ("--ssim-weight", "nan", "--ssim-weight must be a finite number, got nan"),
        ("--init-opacity", "1", "--init-opacity must be in (0, 1), got 1.0"),
        ("--sh-degree", "4", "--sh-degree must be in [0, 3], got 4"),
    ],
)
def test_numeric_options_are_checked_before_any_work(tiny_scene, tmp_path, capsys, option, value, message):
    out = tmp_path / "never"
    argv = ["train", "--data", str(tiny_scene), "--out", str(out), "--no-progress", "--device", DEFAULT_DEVICE]
    assert cli_main([*argv, option, value]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("optimizer", ["adam", "selective"])
def test_a_step_waits_for_the_gpu_once_on_cuda(tiny_scene, tmp_path, monkeypatch, optimizer, device):
    """Between refinements and log points a CUDA step makes the host wait for the GPU once: where
    the render reads its pair count to size the sort (issue 21). torch's sync debug mode raises on
    any other synchronising call (.item(), a blocking copy, a shape read from the device)."""
    if device != "cuda":
        pytest.skip("host synchronisations are a CUDA matter")
    from cdcgs import render

    reads = []
    real = render._count_reader

    def allowed(nonfinite, names):
        read = real(nonfinite, names)

        def read_count(offsets):
            reads.append(1)
            torch.cuda.set_sync_debug_mode("default")
            try:
                return read(offsets)
            finally:
                torch.cuda.set_sync_debug_mode("error")

        return read_count

    monkeypatch.setattr(render, "_count_reader", allowed)
    # the counted step (the default replays steps as CUDA graphs, which read no count)
    trainer = Trainer(tiny_config(tiny_scene, tmp_path, device="cuda", iters=30, optimizer=optimizer, cuda_graph=False))
    trainer._setup()
    for _ in range(3):  # kernels compiled, the allocator's blocks in place
        trainer.train_step()
    torch.cuda.synchronize()
    reads.clear()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            trainer.train_step()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert len(reads) == 3, "one pair count read per step"
