"""The benchmark suite: cdcgs next to its CUDA peer, measured in the same process, as ratios.

    python benchmarks/run.py [--sections raster stages knn complexity training] [--out suite.json]

Sections (each prints its part of one table; everything lands in one JSON file):

- raster: forward and forward+backward (loss = image.sum()) on the shared workload
  (../shared/bench/workload.py, or ``--workload``) at ``--sizes``, median of ``--iters`` after
  ``--warmup``, CUDA events; peak memory; tile intersections; cdcgs / gsplat ratios; image agreement.
- stages: the same forward+backward under torch.profiler (CUPTI sees Warp's kernels as well as
  torch's and gsplat's): GPU kernel time per stage and iteration, by kernel name: projection,
  SH colour, binning with sort, blend forward, blend backward, SH backward, projection backward,
  and the rest (torch's fills, copies, reductions). The gap between the event time of a whole
  iteration and the sum of its kernels is launch overhead and host synchronisation.
- knn: exact 3-NN of every point (what initialisation needs) with cdcgs, next to what gsplat's
  trainer uses (scikit-learn's NearestNeighbors on the CPU), on clustered point sets and, when
  given, a COLMAP scene's points3D (``--scene``).
- complexity: the CDC-GS Γ pass for one view (``cdcgs.complexity.gaussian_complexity`` after a
  forward render) at ``--sizes``, next to gsplat's forward render of the same view (the least a
  CUDA implementation must run to get the weights).
- training: a finished ``cdcgs train`` output folder (``--training-run``): iterations per second
  over the whole run, training time, peak GPU memory, test PSNR; the peer's full run is quoted from
  ``--peer-training`` (a JSON file) when it was not measured in this run, and marked so.

gsplat 1.5.3 is the peer; where it does not import the sections time cdcgs alone.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import bench_rasterize
from bench_knn import make_points, time_cdcgs

import cdcgs

STAGES = [
    ("projection", ("project_gaussians", "projection_ewa_3dgs_fused_fwd")),
    ("sh colour", ("sh_to_color", "spherical_harmonics_fwd")),
    (
        "binning + sort",
        ("count_tiles", "gather_counts", "emit_keys", "tile_ranges", "intersect_", "radix", "scan", "sort"),
    ),
    ("blend forward", ("blend_forward", "rasterize_to_pixels_3dgs_fwd")),
    ("blend backward", ("blend_backward", "rasterize_to_pixels_3dgs_bwd")),
    ("sh colour backward", ("spherical_harmonics_bwd",)),
    ("projection backward", ("projection_ewa_3dgs_fused_bwd",)),
    ("loss (L1 + D-SSIM)", ("ssim_l1",)),
    ("optimizer (Adam)", ("adam",)),  # ours (fused_adam_kernel) and torch's (FusedAdamMathFunctor)
    ("communication (NCCL)", ("nccl",)),  # on a stream of its own: it may overlap the others
]


def stage_of(kernel: str) -> str:
    """The stage a GPU kernel belongs to, from its name (Warp names adjoints ``*_backward``)."""
    name = kernel.lower()
    if "backward" in name:  # Warp's generated adjoints end in _cuda_kernel_backward
        if "sh_to_color" in name:
            return "sh colour backward"
        if "project_gaussians" in name:
            return "projection backward"
    for stage, keys in STAGES:
        if any(key in name for key in keys):
            return stage
    return "other (torch)"


def kernel_times(fn, iters: int) -> tuple[dict[str, float], dict[str, float]]:
    """GPU time per stage and per kernel name (ms per call of ``fn``), from torch.profiler."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(iters):
            fn()
        torch.cuda.synchronize()
    totals: dict[str, float] = {}
    kernels: dict[str, float] = {}
    for event in prof.events():
        if event.device_type != DeviceType.CUDA:
            continue
        ms = event.time_range.elapsed_us() / 1e3 / iters
        stage = stage_of(event.name)
        totals[stage] = totals.get(stage, 0.0) + ms
        kernels[event.name] = kernels.get(event.name, 0.0) + ms
    return totals, kernels


def device_name(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"


# --------------------------------------------------------------------------------------------
# Sections


def section_raster(args, device, workload, report):
    for n in args.sizes:
        scene = workload.make_scene(n, device=args.device)
        leaves, renderers = bench_rasterize.make_renderers(scene)
        images = {}
        for name, render in renderers.items():
            image, intersections = render()
            images[name] = image.detach()
            step = _forward_backward(render, leaves)
            row = {
                "section": "raster",
                "renderer": name,
                "n": n,
                "forward_ms": bench_rasterize.timed(
                    lambda render=render: _no_grad(render), device, args.warmup, args.iters
                ),
                "forward_backward_ms": bench_rasterize.timed(step, device, args.warmup, args.iters),
                "intersections": intersections,
                "peak_gb": bench_rasterize.peak_gb(step, device),
            }
            if "stages" in args.sections and device.type == "cuda":
                row["stages_ms"], kernels = kernel_times(step, max(3, args.iters // 3))
                # the slowest kernels by name (JSON only): where a stage's time goes
                row["kernels_ms"] = dict(sorted(kernels.items(), key=lambda kv: -kv[1])[:25])
            report(row)
        if "gsplat" in images:
            diff = (images["cdcgs"] - images["gsplat"]).abs()
            psnr = -10 * torch.log10((diff**2).mean().clamp_min(1e-20)).item()
            report({"section": "agreement", "n": n, "max_abs_diff": diff.max().item(), "psnr_db": psnr})
        del scene, leaves, renderers, images
        if device.type == "cuda":
            torch.cuda.empty_cache()


def _no_grad(render):
    with torch.no_grad():
        render()


def _forward_backward(render, leaves):
    def step():
        image, _ = render()
        image.sum().backward()
        for t in leaves.values():
            t.grad = None

    return step


def section_knn(args, device, report):
    sets = [(f"clustered {n // 1000}k", torch.from_numpy(make_points("clustered", n))) for n in args.knn_sizes]
    if args.scene:
        sets.insert(0, (f"{os.path.basename(os.path.normpath(args.scene))} points3D", _scene_points(args.scene)))
    for label, points in sets:
        ms, _ = time_cdcgs(points.to(device), 3, args.iters)
        row = {"section": "knn", "points": label, "n": points.shape[0], "cdcgs_ms": ms}
        try:
            from sklearn.neighbors import NearestNeighbors
        except ImportError:
            pass
        else:
            numpy_points = points.numpy()
            t0 = time.perf_counter()
            NearestNeighbors(n_neighbors=4, metric="euclidean").fit(numpy_points).kneighbors(numpy_points)
            row["peer"] = "scikit-learn NearestNeighbors (gsplat's trainer), CPU"
            row["peer_ms"] = (time.perf_counter() - t0) * 1e3
        report(row)


def _scene_points(path: str) -> torch.Tensor:
    import numpy as np

    from cdcgs.io.colmap import find_model_dir, read_reconstruction

    reconstruction = read_reconstruction(find_model_dir(path))
    return torch.from_numpy(np.array([p.xyz for p in reconstruction.points3D.values()], dtype=np.float32))


def section_complexity(args, device, workload, report):
    from cdcgs.complexity import gaussian_complexity

    for n in args.sizes:
        scene = workload.make_scene(n, device=args.device)
        leaves, renderers = bench_rasterize.make_renderers(scene)
        generator = torch.Generator(device="cpu").manual_seed(0)
        hf_map = torch.randint(0, 256, (scene["height"], scene["width"]), generator=generator, dtype=torch.uint8).to(
            device
        )
        with torch.no_grad():
            _, _, info = cdcgs.rasterize(
                leaves["means"],
                leaves["quats"],
                leaves["scales"],
                leaves["opacities"],
                leaves["sh"],
                viewmat=scene["viewmat"].cpu(),
                K=scene["K"].cpu(),
                width=scene["width"],
                height=scene["height"],
            )
        row = {
            "section": "complexity",
            "n": n,
            "gamma_pass_ms": bench_rasterize.timed(
                lambda info=info, hf_map=hf_map: gaussian_complexity(info, hf_map), device, args.warmup, args.iters
            ),
        }
        for name, render in renderers.items():
            row[f"{name}_forward_ms"] = bench_rasterize.timed(
                lambda render=render: _no_grad(render), device, args.warmup, args.iters
            )
        report(row)
        del scene, leaves, renderers, info


def section_training(args, report):
    if not args.training_run:
        print("training: no --training-run given; skipped", file=sys.stderr)
        return
    for path in args.training_run:
        with open(os.path.join(path, "metrics.json")) as f:
            metrics = json.load(f)
        report(
            {
                "section": "training",
                "run": path,
                "strategy": metrics["strategy"].get("name"),
                "iterations": metrics["iterations"],
                "iterations_per_second": metrics["iterations_per_second"],
                "train_seconds": metrics["train_seconds"],
                "peak_gpu_memory_gb": metrics["peak_gpu_memory_gb"],
                "psnr": metrics["test"].get("psnr"),
                "ssim": metrics["test"].get("ssim"),
                "lpips_vgg": metrics["test"].get("lpips_vgg"),
                "lpips_alex": metrics["test"].get("lpips_alex"),
                "num_gaussians": metrics["num_gaussians"],
                "device": metrics["device"],
            }
        )
    if args.peer_training:
        with open(args.peer_training) as f:
            peer = json.load(f)
        report({"section": "training", "run": "peer (quoted, not measured in this run)", **peer})


# --------------------------------------------------------------------------------------------
# One table


def print_tables(rows: list[dict], machine: str) -> None:
    print(f"\n## cdcgs benchmark suite on {machine}\n")
    raster = {(r["renderer"], r["n"]): r for r in rows if r["section"] == "raster"}
    if raster:
        print(
            "| N | cdcgs fwd ms | gsplat fwd ms | ratio | cdcgs fwd+bwd ms | gsplat fwd+bwd ms | ratio | peak GB cdcgs / gsplat |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for (name, n), r in raster.items():
            if name != "cdcgs":
                continue
            p = raster.get(("gsplat", n))
            print(
                f"| {n:,} | {r['forward_ms']:.2f} | {_f(p, 'forward_ms')} | {_ratio(r, p, 'forward_ms')} | "
                f"{r['forward_backward_ms']:.2f} | {_f(p, 'forward_backward_ms')} | {_ratio(r, p, 'forward_backward_ms')} | "
                f"{r['peak_gb']:.2f} / {_f(p, 'peak_gb')} |"
            )
        staged = [r for r in raster.values() if "stages_ms" in r]
        if staged:
            names = [s for s, _ in STAGES if any(s in r["stages_ms"] for r in staged)] + ["other (torch)"]
            print("\nGPU kernel time per forward+backward, ms (torch.profiler)\n")
            print("| stage | " + " | ".join(f"{r['renderer']} {r['n'] // 1000}k" for r in staged) + " |")
            print("|---|" + "---|" * len(staged))
            for stage in [*names, "sum of kernels", "event time"]:
                cells = []
                for r in staged:
                    if stage == "sum of kernels":
                        cells.append(f"{sum(r['stages_ms'].values()):.2f}")
                    elif stage == "event time":
                        cells.append(f"{r['forward_backward_ms']:.2f}")
                    else:
                        cells.append(f"{r['stages_ms'].get(stage, 0.0):.2f}")
                print(f"| {stage} | " + " | ".join(cells) + " |")
    for r in rows:
        if r["section"] == "agreement":
            print(
                f"\nn={r['n']:,}: cdcgs vs gsplat image PSNR {r['psnr_db']:.1f} dB, max |diff| {r['max_abs_diff']:.1e}"
            )
    knn_rows = [r for r in rows if r["section"] == "knn"]
    if knn_rows:
        print("\n| KNN (k=3) | N | cdcgs ms | peer ms | ratio |\n|---|---|---|---|---|")
        for r in knn_rows:
            print(
                f"| {r['points']} | {r['n']:,} | {r['cdcgs_ms']:.1f} | {_f(r, 'peer_ms', 1)} | {_ratio_keys(r, 'cdcgs_ms', 'peer_ms')} |"
            )
    cx = [r for r in rows if r["section"] == "complexity"]
    if cx:
        print(
            "\n| Γ pass | N | Γ pass ms (one view) | cdcgs forward ms | gsplat forward ms | Γ / gsplat forward |\n|---|---|---|---|---|---|"
        )
        for r in cx:
            print(
                f"| complexity | {r['n']:,} | {r['gamma_pass_ms']:.2f} | {r['cdcgs_forward_ms']:.2f} | "
                f"{_f(r, 'gsplat_forward_ms')} | {_ratio_keys(r, 'gamma_pass_ms', 'gsplat_forward_ms')} |"
            )
    tr = [r for r in rows if r["section"] == "training"]
    if tr:
        print(
            "\n| training run | it/s | train s | peak GB | PSNR | SSIM | LPIPS-VGG | LPIPS-Alex | Gaussians |"
            "\n|---|---|---|---|---|---|---|---|---|"
        )
        for r in tr:
            print(
                f"| {r['run']} | {_f(r, 'iterations_per_second', 1)} | {_f(r, 'train_seconds', 0)} | "
                f"{_f(r, 'peak_gpu_memory_gb')} | {_f(r, 'psnr')} | {_f(r, 'ssim', 3)} | {_f(r, 'lpips_vgg', 3)} | "
                f"{_f(r, 'lpips_alex', 3)} | {r.get('num_gaussians', '-')} |"
            )


def _f(row, key, digits=2):
    return "-" if not row or row.get(key) is None else f"{row[key]:.{digits}f}"


def _ratio(row, peer, key):
    return "-" if not peer else f"{row[key] / peer[key]:.2f}"


def _ratio_keys(row, key, peer_key):
    return "-" if row.get(peer_key) is None else f"{row[key] / row[peer_key]:.2f}"


def main(argv=None):
    sections = ["raster", "stages", "knn", "complexity", "training"]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", nargs="+", choices=sections, default=sections, help="what to run")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000, 3_000_000], help="Gaussian counts")
    parser.add_argument(
        "--knn-sizes", type=int, nargs="+", default=[1_000_000, 3_000_000], help="clustered point-set sizes for knn"
    )
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument(
        "--workload", default=bench_rasterize.DEFAULT_WORKLOAD, help="path of the shared bench/workload.py"
    )
    parser.add_argument("--scene", default=None, help="COLMAP scene whose points3D the knn section also times")
    parser.add_argument("--training-run", nargs="+", default=None, help="finished cdcgs train output folders")
    parser.add_argument("--peer-training", default=None, help="JSON of the peer's training run to quote")
    parser.add_argument("--warmup", type=int, default=3, help="untimed iterations before timing")
    parser.add_argument("--iters", type=int, default=30, help="timed iterations (median reported)")
    parser.add_argument("--out", default=None, help="write all rows as JSON here")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    machine = device_name(device)
    rows: list[dict] = []

    def report(row):
        row["device"] = row.get("device", machine)
        rows.append(row)
        print(json.dumps(row), flush=True)

    needs_workload = {"raster", "stages", "complexity"} & set(args.sections)
    workload = bench_rasterize.load_workload(args.workload) if needs_workload else None
    if {"raster", "stages"} & set(args.sections):
        section_raster(args, device, workload, report)
    if "knn" in args.sections:
        section_knn(args, device, report)
    if "complexity" in args.sections:
        section_complexity(args, device, workload, report)
    if "training" in args.sections:
        section_training(args, report)
    print_tables(rows, machine)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": machine, "date": time.strftime("%Y-%m-%d"), "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
