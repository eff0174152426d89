"""GPU memory and time of what a held-out evaluation computes besides its renders, on one batch of
image pairs: LPIPS-VGG, LPIPS-Alex, SSIM and PSNR, with and without cuDNN.

    python benchmarks/eval_memory.py [--device cuda] [--size 800x533] [--images 2] [--data SCENE]
        [--settings wscap v7 native cudnn] [--wscap 256] [--repeats 3] [--out eval_memory.json]

Why: the evaluations of the bonsai trainings peaked at 37.5 GB on an H100 (torch's
max_memory_allocated over evaluate(), ``peak_gpu_memory_eval_gb``) against 1-2.8 GB for their
training, whatever the number of Gaussians. The suspect is the workspace of the cuDNN engine that
PyTorch takes for LPIPS's convolutions: the first of cuDNN's heuristics whose workspace it can
allocate, which on an 80 GB GPU may be tens of GB.

The pairs: ``--images`` images of ``--size`` (width x height) of seeded random content, each
against a noisy copy; or, with ``--data``, the first test views of that scene against themselves
shifted by a few pixels, with a little noise. LPIPS scores them through the evaluation's own ``LpipsMetric.scores``
(its batches of at most 1M pixels, its channels-last layout), SSIM and PSNR one pair at a time as
``evaluate()`` does. LPIPS has the converted weights of the cache (``cdcgs weights lpips``), or
random weights of the same shapes (``--weights random``, or when the cache has none, as the output
says): its memory and time do not depend on the weights.

Settings (each measures the four parts):

- ``native``: LPIPS as cdcgs runs it now, on torch's own convolution kernels (cuDNN off, TF32
  off); SSIM and PSNR with cuDNN off too.
- ``cudnn``: LPIPS as it ran before, on cuDNN with its deterministic algorithms, benchmark mode
  off, TF32 off (``LPIPS(cudnn=True)``); SSIM and PSNR as ``evaluate()`` calls them (torch's
  defaults).
- ``wscap``: ``cudnn`` in a process of its own with ``CUDNN_CONV_WSCAP_DBG=--wscap`` (MiB: cuDNN's
  cap on its convolution workspaces, which it may read once per process).
- ``v7``: ``cudnn`` in a process of its own with ``TORCH_CUDNN_V8_API_DISABLED=1`` (PyTorch's
  older cuDNN API).

The settings of their own processes run first, while this one holds no GPU memory. Columns: peak =
``torch.cuda.max_memory_allocated`` over the part's calls (the cache emptied and the peak reset
before each part); extra = peak less what was allocated before the part; reserved =
``max_memory_reserved``; largest = the largest single allocation in the allocator's history (n/a
where this torch keeps none); first = seconds of the first call (cuDNN's choice of engines
included); then = mean seconds of ``--repeats`` calls more; max|d| = the largest difference of the
part's scores from the ``native`` setting's. On the CPU the memory columns are n/a and every
setting is the same computation.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import time

import torch

from cdcgs.lpips import LPIPS, WeightsUnavailable, load_lpips
from cdcgs.train.evaluate import LPIPS_NETS, LpipsMetric
from cdcgs.train.loss import psnr, ssim

SETTINGS = ("wscap", "v7", "native", "cudnn")  # the order they run in
OWN_PROCESS = ("wscap", "v7")
CHILD_LINE = "eval_memory rows: "  # how a setting's process hands back its rows on stdout
MEMORY_KEYS = ("peak_gb", "extra_gb", "reserved_gb", "largest_allocation_gb", "device_used_gb")


def parse_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(value) for value in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a size is WIDTHxHEIGHT, e.g. 800x533, got {text!r}") from None
    if min(width, height) < 31:
        raise argparse.ArgumentTypeError(f"LPIPS-Alex needs at least 31 x 31 pixels, got {text!r}")
    return width, height


def setting_environment(setting: str, wscap: int) -> dict[str, str]:
    """The environment variables that a setting run in its own process sets."""
    if setting == "wscap":
        return {"CUDNN_CONV_WSCAP_DBG": str(wscap)}
    if setting == "v7":
        return {"TORCH_CUDNN_V8_API_DISABLED": "1"}
    return {}


def image_pairs(args, device) -> tuple[list[torch.Tensor], list[torch.Tensor], str]:
    """(images, targets, description): [H, W, 3] float32 in [0, 1] on ``device``, as ``evaluate``
    holds a render and its photo."""
    if args.data:
        from cdcgs.io.scene import load_scene

        scene = load_scene(args.data, factor=args.factor, progress=False)
        views = (scene.test or scene.train)[: args.images]
        targets = [view.image.float() / 255.0 for view in views]
        generator = torch.Generator().manual_seed(args.seed)
        # A render a few pixels off, and not equal to a flat view.
        images = [
            (t.roll((3, 5), dims=(0, 1)) + 0.02 * torch.randn(t.shape, generator=generator)).clamp(0, 1)
            for t in targets
        ]
        names = ", ".join(view.name for view in views)
        source = f"{args.data}: {names} against themselves shifted by (3, 5) px, with noise (seed {args.seed})"
    else:
        generator = torch.Generator().manual_seed(args.seed)
        width, height = args.size
        targets = [torch.rand(height, width, 3, generator=generator) for _ in range(args.images)]
        images = [(t + 0.1 * torch.randn(t.shape, generator=generator)).clamp(0, 1) for t in targets]
        source = f"{args.images} random images of {width} x {height} (seed {args.seed}) against noisy copies"
    return [x.to(device) for x in images], [x.to(device) for x in targets], source


def random_lpips(net: str, seed: int) -> LPIPS:
    """LPIPS with random weights of the trained ones' shapes (He initialisation, positive heads)."""
    generator = torch.Generator().manual_seed(seed)
    model = LPIPS(net)
    state = {}
    for name, tensor in model.state_dict().items():
        if name.startswith("heads."):
            state[name] = torch.rand(tensor.shape, generator=generator) * 0.2
        elif name.endswith("weight"):
            state[name] = torch.randn(tensor.shape, generator=generator) * (2.0 / tensor[0].numel()) ** 0.5
        else:
            state[name] = torch.randn(tensor.shape, generator=generator) * 0.1
    model.load_state_dict(state)
    return model


def lpips_networks(weights: str, device, seed: int) -> tuple[dict[str, LPIPS], str]:
    nets, notes = {}, []
    for name in LPIPS_NETS:
        if weights == "cache":
            try:
                nets[name] = load_lpips(name, device)
                notes.append(f"LPIPS-{name}: the converted weights")
                continue
            except WeightsUnavailable as err:
                notes.append(f"LPIPS-{name}: random weights, none in the cache ({err})")
        else:
            notes.append(f"LPIPS-{name}: random weights")
        nets[name] = random_lpips(name, seed).to(device)
    return nets, "; ".join(notes)


@contextlib.contextmanager
def cudnn_off():
    saved = torch.backends.cudnn.enabled
    torch.backends.cudnn.enabled = False
    try:
        yield
    finally:
        torch.backends.cudnn.enabled = saved


def synchronize(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def start_history() -> bool:
    """Start the allocator's history of allocations (no stack traces); False where this torch
    has none."""
    try:
        torch.cuda.memory._record_memory_history(enabled="all", context=None, stacks="python", max_entries=1_000_000)
        return True
    except Exception:  # a private API: its absence costs one column, not the run
        return False


def largest_allocation(recording: bool, device) -> float | None:
    """GB of the largest allocation since :func:`start_history`, which it stops (the history is
    then cleared)."""
    if not recording:
        return None
    try:
        snapshot = torch.cuda.memory._snapshot(device)
    except Exception:
        snapshot = {}
    finally:
        with contextlib.suppress(Exception):
            torch.cuda.memory._record_memory_history(enabled=None)
    sizes = [
        entry.get("size", 0)
        for trace in snapshot.get("device_traces", [])
        for entry in trace
        if entry.get("action") == "alloc"
    ]
    return max(sizes) / 1e9 if sizes else None


def measure(setting: str, part: str, call, device, repeats: int) -> dict:
    """One part under one setting: its scores, peak memory and seconds."""
    cuda = device.type == "cuda"
    row = {"setting": setting, "part": part}
    if cuda:
        synchronize(device)
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
        before = torch.cuda.memory_allocated(device)
        recording = start_history()
    with torch.no_grad():
        start = time.perf_counter()
        scores = call()
        synchronize(device)
        row["first_s"] = time.perf_counter() - start
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            call()
            synchronize(device)
            seconds.append(time.perf_counter() - start)
    row["then_s"] = statistics.mean(seconds) if seconds else None
    row["scores"] = [None if s is None else float(s) for s in scores]
    row.update(dict.fromkeys(MEMORY_KEYS))
    if cuda:
        peak = torch.cuda.max_memory_allocated(device)
        free, total = torch.cuda.mem_get_info(device)
        row.update(
            peak_gb=peak / 1e9,
            extra_gb=(peak - before) / 1e9,
            reserved_gb=torch.cuda.max_memory_reserved(device) / 1e9,
            largest_allocation_gb=largest_allocation(recording, device),
            device_used_gb=(total - free) / 1e9,
        )
    return row


def run_setting(setting: str, cudnn: bool, nets, images, targets, device, repeats: int) -> list[dict]:
    """The four parts, with LPIPS on cuDNN (as before) or on torch's own kernels (as now)."""
    rows = []
    for name, net in nets.items():
        net.cudnn = cudnn
        metric = LpipsMetric(device, nets={name: net})
        rows.append(
            measure(
                setting,
                f"lpips_{name}",
                lambda metric=metric, name=name: metric.scores(images, targets)[f"lpips_{name}"],
                device,
                repeats,
            )
        )
    for part, score in (("ssim", ssim), ("psnr", psnr)):

        def call(score=score):
            with contextlib.nullcontext() if cudnn else cudnn_off():
                return [score(image, target).item() for image, target in zip(images, targets)]

        rows.append(measure(setting, part, call, device, repeats))
    return rows


def run_in_own_process(setting: str, args, argv: list[str]) -> list[dict]:
    """The ``cudnn`` computation in a new process (given ``argv``, this one's options) with the
    setting's environment variables."""
    import cdcgs

    env = dict(os.environ, **setting_environment(setting, args.wscap))
    package_root = os.path.dirname(os.path.dirname(os.path.abspath(cdcgs.__file__)))
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH")) if p)
    command = [sys.executable, os.path.abspath(__file__), *argv, "--child", setting]
    done = subprocess.run(command, env=env, stdout=subprocess.PIPE, text=True, check=False)
    for line in reversed(done.stdout.splitlines()):
        if line.startswith(CHILD_LINE):
            return json.loads(line[len(CHILD_LINE) :])
    return [{"setting": setting, "part": "all", "error": f"its process exited with {done.returncode}, no rows"}]


def compare(rows: list[dict]) -> None:
    """Each row's largest score difference from the ``native`` row of its part (else the first)."""
    reference = {}
    for row in rows:
        if "scores" in row and (row["setting"] == "native" or row["part"] not in reference):
            reference[row["part"]] = row["scores"]
    for row in rows:
        if "scores" not in row:
            continue
        pairs = [(a, b) for a, b in zip(row["scores"], reference[row["part"]]) if a is not None and b is not None]
        row["max_abs_diff"] = max((abs(a - b) for a, b in pairs), default=None)


def table(rows: list[dict]) -> str:
    def number(value, digits):
        return "n/a" if value is None else f"{value:.{digits}f}"

    header = ("setting", "part", "peak GB", "extra GB", "reserved GB", "largest GB", "first s", "then s", "max|d|")
    lines = [header]
    for row in rows:
        if "error" in row:
            lines.append((row["setting"], row["part"], row["error"], "", "", "", "", "", ""))
            continue
        lines.append(
            (
                row["setting"],
                row["part"],
                number(row["peak_gb"], 2),
                number(row["extra_gb"], 2),
                number(row["reserved_gb"], 2),
                number(row["largest_allocation_gb"], 2),
                number(row["first_s"], 3),
                number(row["then_s"], 3),
                "n/a" if row.get("max_abs_diff") is None else f"{row['max_abs_diff']:.1e}",
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(line, widths)).rstrip() for line in lines)


def main(argv: list[str] | None = None) -> dict | None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--size", type=parse_size, default=(800, 533), help="WIDTHxHEIGHT (default 800x533)")
    parser.add_argument("--images", type=int, default=2, help="image pairs (default 2: one LPIPS batch)")
    parser.add_argument("--data", default=None, help="a scene folder: its first test views instead of random images")
    parser.add_argument("--factor", type=int, default=None, help="with --data: the scene's downsampling factor")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--weights", choices=("cache", "random"), default="cache", help="LPIPS weights (default cache)")
    parser.add_argument("--settings", nargs="+", choices=SETTINGS, default=list(SETTINGS))
    parser.add_argument("--wscap", type=int, default=256, help="MiB, for the wscap setting (default 256)")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls after the first (default 3)")
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    images, targets, source = image_pairs(args, device)
    nets, weights = lpips_networks(args.weights, device, args.seed)
    if args.child is not None:  # a setting's own process: the cudnn computation, rows on stdout
        rows = run_setting(args.child, True, nets, images, targets, device, args.repeats)
        names = setting_environment(args.child, args.wscap)
        for row in rows:
            row["environment"] = {name: os.environ.get(name) for name in names}
        print(CHILD_LINE + json.dumps(rows), flush=True)
        return None
    forwarded = [
        *("--device", args.device, "--size", "x".join(map(str, args.size)), "--images", str(args.images)),
        *("--seed", str(args.seed), "--weights", args.weights, "--wscap", str(args.wscap)),
        *("--repeats", str(args.repeats)),
        *(("--data", args.data) if args.data else ()),
        *(("--factor", str(args.factor)) if args.factor is not None else ()),
    ]
    rows = []
    for setting in (s for s in SETTINGS if s in args.settings):
        if setting in OWN_PROCESS:
            rows += run_in_own_process(setting, args, forwarded)
        else:
            rows += run_setting(setting, setting == "cudnn", nets, images, targets, device, args.repeats)
    compare(rows)
    cuda = device.type == "cuda"
    result = {
        "device": torch.cuda.get_device_name(device) if cuda else "cpu",
        "torch": torch.__version__,
        "cudnn": torch.backends.cudnn.version() if cuda else None,
        "gpu_total_gb": torch.cuda.mem_get_info(device)[1] / 1e9 if cuda else None,
        "pairs": source,
        "weights": weights,
        "wscap_mib": args.wscap,
        "rows": rows,
    }
    print(f"{result['device']}, torch {result['torch']}, cuDNN {result['cudnn']}; {source}; {weights}")
    print(table(rows))
    legend = {
        "native": "LPIPS off cuDNN (cdcgs now), SSIM/PSNR off cuDNN",
        "cudnn": "LPIPS on cuDNN, deterministic, TF32 off (before), SSIM/PSNR as evaluate() runs them",
        "wscap": f"cudnn with CUDNN_CONV_WSCAP_DBG={args.wscap} (own process)",
        "v7": "cudnn with TORCH_CUDNN_V8_API_DISABLED=1 (own process)",
    }
    print("; ".join(f"{name}: {legend[name]}" for name in SETTINGS if name in args.settings))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)
    return result


if __name__ == "__main__":
    main()
