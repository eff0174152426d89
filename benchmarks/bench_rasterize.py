"""Rasterizer timing on the shared workload, next to gsplat measured in the same process.

    python benchmarks/bench_rasterize.py [--sizes 100000 1000000 3000000] [--capacity 1.25 2]
        [--out results.json]

The workload is the scene every peer is measured on: a module with ``make_scene(n, device=...)``,
given with ``--workload PATH`` (default: ``DEFAULT_WORKLOAD`` below). For each size: forward, and forward+backward with
loss = image.sum(), median of ``--iters`` timed iterations after ``--warmup`` warm-ups, timed with
CUDA events on the GPU (wall clock on the CPU); peak memory from torch's allocator (which backs
every buffer cdcgs allocates); tile intersections. gsplat 1.5.3 ``rasterization(packed=False)``
runs on the same scene when it imports; both renders are compared as a cross-check of conventions.

Each render is also timed pipelined: ``--iters`` forward+backward iterations launched back to
back with one synchronisation at the end (wall clock / iterations), as a training issues them.
A counted render (cdcgs, gsplat) waits for its intersection count inside every iteration; with
``--capacity M`` cdcgs also renders into ceil(M x count) slots without reading anything back
(``rasterize(capacity=)``: no wait, but the sort's work grows with the slots), so the two
pipelined columns show what a training step without the count read would gain or lose. Its
images must equal the counted render's (checked, with ``info.check()`` for overflow).
"""

import argparse
import importlib.util
import json
import math
import os
import statistics
import sys
import time

import torch

import cdcgs
import cdcgs.render

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from kernel_options import add_kernel_options, check_kernel_options, kernel_options

DEFAULT_WORKLOAD = os.path.join(HERE, "..", "..", "shared", "bench", "workload.py")


def load_workload(path):
    if not os.path.exists(path):
        sys.exit(f"workload not found at {path}: pass --workload PATH to the shared bench/workload.py")
    spec = importlib.util.spec_from_file_location("workload", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def timed(fn, device, warmup, iters):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(iters):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def pipelined(fn, device, warmup, iters):
    """Milliseconds per call of ``iters`` calls issued back to back, one synchronisation at the end."""
    for _ in range(warmup):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for _ in range(iters):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return (time.perf_counter() - t0) * 1e3 / iters


def peak_gb(fn, device):
    if device.type != "cuda":
        return float("nan")
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    fn()
    torch.cuda.synchronize()
    return torch.cuda.max_memory_allocated() / 1e9


def make_renderers(scene, margins=()):
    """name -> render(): (image, intersections); cdcgs counted, cdcgs into ceil(margin x count)
    slots for each margin, and gsplat where it imports."""
    leaves = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "sh")}
    w, h = scene["width"], scene["height"]
    # Checked and built once, as a training holds its views' cameras.
    camera = cdcgs.prepare_camera(scene["viewmat"].cpu(), scene["K"].cpu(), w, h)

    def ours(capacity=None):
        image, _, info = cdcgs.rasterize(
            leaves["means"],
            leaves["quats"],
            leaves["scales"],
            leaves["opacities"],
            leaves["sh"],
            camera=camera,
            sh_degree=scene["sh_degree"],
            capacity=capacity,
        )
        return image, info

    def counted():
        image, info = ours()
        return image, info.num_intersections

    renderers = {"cdcgs": counted}
    count = counted()[1] if margins else 0
    for margin in margins:
        capacity = max(1, math.ceil(margin * count))

        def within(capacity=capacity):
            return ours(capacity)[0], count

        within.check = lambda capacity=capacity: ours(capacity)[1].check()  # reads the device's flags
        renderers[f"cdcgs capacity {margin:g}x"] = within
    try:
        from gsplat import rasterization
    except ImportError as err:
        print(f"gsplat not importable ({err}); timing cdcgs alone", file=sys.stderr)
        return leaves, renderers

    def peer():
        image, _, meta = rasterization(
            leaves["means"],
            leaves["quats"],
            leaves["scales"],
            leaves["opacities"],
            leaves["sh"],
            scene["viewmat"][None],
            scene["K"][None],
            w,
            h,
            sh_degree=scene["sh_degree"],
            packed=False,
        )
        return image[0], int(meta["isect_ids"].numel())

    renderers["gsplat"] = peer
    return leaves, renderers


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000, 3_000_000], help="Gaussian counts")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument("--workload", default=DEFAULT_WORKLOAD, help="path of the shared bench/workload.py")
    parser.add_argument("--warmup", type=int, default=3, help="untimed iterations before timing")
    parser.add_argument("--iters", type=int, default=30, help="timed iterations (median reported)")
    parser.add_argument(
        "--capacity",
        type=float,
        nargs="*",
        default=[],
        metavar="M",
        help="also time cdcgs into ceil(M x count) slots without the count read (M >= 1), e.g. 1.25 2",
    )
    add_kernel_options(parser)
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    args = parser.parse_args(argv)
    check_kernel_options(parser, args)
    if any(not math.isfinite(m) or m < 1.0 for m in args.capacity):
        parser.error(f"--capacity: margins must be at least 1 (room for every pair), got {args.capacity}")
    with kernel_options(args):
        return measure(args)


def measure(args):
    """Time every renderer at every size of ``args``, print the table and write the JSON."""
    device = torch.device(args.device)
    workload = load_workload(args.workload)
    rows = []
    for n in args.sizes:
        scene = workload.make_scene(n, device=args.device)
        leaves, renderers = make_renderers(scene, args.capacity)
        images = {}
        for name, render in renderers.items():
            image, intersections = render()
            images[name] = image.detach()
            if hasattr(render, "check"):  # room for every pair, and the counted render's image
                render.check()
                if not torch.equal(images[name], images["cdcgs"]):
                    sys.exit(f"n={n}: {name} renders another image than the counted render")

            def forward(render=render):
                with torch.no_grad():
                    render()

            def forward_backward(render=render, leaves=leaves):
                image, _ = render()
                image.sum().backward()
                for t in leaves.values():
                    t.grad = None

            row = {
                "renderer": name,
                "n": n,
                "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
                "forward_ms": timed(forward, device, args.warmup, args.iters),
                "forward_backward_ms": timed(forward_backward, device, args.warmup, args.iters),
                "pipelined_ms": pipelined(forward_backward, device, args.warmup, args.iters),
                "intersections": intersections,
                "peak_gb": peak_gb(forward_backward, device),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
        if "gsplat" in images:
            diff = (images["cdcgs"] - images["gsplat"]).abs()
            mse = (diff**2).mean().item()
            psnr = 10 * torch.log10(torch.tensor(1.0 / max(mse, 1e-20))).item()
            print(f"n={n}: cdcgs vs gsplat image max |diff| {diff.max().item():.2e}, PSNR {psnr:.1f} dB", flush=True)
            rows.append({"renderer": "agreement", "n": n, "max_abs_diff": diff.max().item(), "psnr_db": psnr})
        del scene, leaves, renderers, images
        if device.type == "cuda":
            torch.cuda.empty_cache()

    print()
    print(
        "| N | renderer | forward ms | fwd+bwd ms | fwd+bwd pipelined ms | intersections | peak GB "
        "| fwd ratio | fwd+bwd ratio |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    by_key = {(r["renderer"], r["n"]): r for r in rows if "forward_ms" in r}
    for r in rows:
        if "forward_ms" not in r:
            continue
        peer = by_key.get(("gsplat", r["n"]))
        ratio_f = f"{r['forward_ms'] / peer['forward_ms']:.2f}" if peer else "-"
        ratio_fb = f"{r['forward_backward_ms'] / peer['forward_backward_ms']:.2f}" if peer else "-"
        print(
            f"| {r['n']:,} | {r['renderer']} | {r['forward_ms']:.2f} | {r['forward_backward_ms']:.2f} | "
            f"{r['pipelined_ms']:.2f} | "
            f"{r['intersections'] / 1e6:.2f}M | {r['peak_gb']:.2f} | {ratio_f} | {ratio_fb} |"
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
