"""Where a training step's time goes: every kernel, the loss, the optimizer, the strategy's
bookkeeping, data, host synchronisations, on a real scene at a chosen number of Gaussians.

    python benchmarks/profile_step.py --data SCENE --images images --gaussians 1000000 3000000 \
        [--ply run/point_cloud.ply] [--strategy 3dgs] [--at 20000] [--steps 50] [--out profile.json]

For each count: the trainer is set up as ``cdcgs train`` would be, its model replaced by the
Gaussians of ``--ply`` (a trained model: the realistic workload) or, without one, by the scene's
initial points replicated with jitter; resampled to the count (a random subset, or copies with a
jitter of their own scale). The iteration counter is set to ``--at`` (20000: after densification,
the steady state; 5001: during it, with the gradient statistics but no densification step inside
the window). After ``--warmup`` steps, ``--steps`` steps are timed by the wall clock (a device
synchronisation at both ends only: the step as the training runs it), then the same number under
torch.profiler (CUPTI sees Warp's kernels as well as torch's), with each part of
``Trainer.train_step`` wrapped in a labelled range.

Printed and written to ``--out``: ms per step (wall), the share of it the GPU is busy (the union of
kernel intervals over the profiled window), kernels per step (Warp's and torch's), host
synchronisations and device-to-host copies per step, GPU time per stage (by kernel name) and, per
part of the step, host time and the GPU time of the kernels it launched.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from run import STAGES, stage_of

import cdcgs
from cdcgs.io import read_ply
from cdcgs.train import trainer as trainer_module
from cdcgs.train.config import DataConfig, TrainConfig
from cdcgs.train.model import GaussianModel
from cdcgs.train.ops import make_optimizer
from cdcgs.train.trainer import Trainer

# The parts of a step, in the order they run; each is a labelled range in the profile.
PARTS = [
    "view and learning rate",
    "render forward",
    "loss forward",
    "strategy before backward",
    "backward",
    "guard",
    "strategy observe",
    "optimizer step",
    "zero grad",
    "strategy after step",
]
SYNC_CALLS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cuStreamSynchronize")


def labelled(label, fn):
    def wrapped(*args, **kwargs):
        with torch.profiler.record_function(label):
            return fn(*args, **kwargs)

    return wrapped


def resampled(model: GaussianModel, count: int, generator: torch.Generator) -> GaussianModel:
    """``count`` Gaussians from ``model``: a random subset, or every one plus copies moved by a
    draw of their own scale (as a split would place them)."""
    params = {k: v.detach() for k, v in model.params.items()}
    n = params["means"].shape[0]
    device = params["means"].device
    if count <= n:
        keep = torch.randperm(n, generator=generator, device=device)[:count]
        params = {k: v[keep] for k, v in params.items()}
    else:
        extra = torch.randint(0, n, (count - n,), generator=generator, device=device)
        copies = {k: v[extra].clone() for k, v in params.items()}
        jitter = torch.randn(count - n, 3, generator=generator, device=device)
        copies["means"] += jitter * params["log_scales"][extra].exp()
        params = {k: torch.cat([v, copies[k]]) for k, v in params.items()}
    params = {k: v.contiguous() for k, v in params.items()}
    return GaussianModel(params, max_sh_degree=model.max_sh_degree, sh_degree=model.max_sh_degree)


def prepared(args, count: int, out: str) -> Trainer:
    config = TrainConfig(
        data=DataConfig(data=args.data, images=args.images),
        out=out,
        strategy=args.strategy,
        device="cuda" if torch.cuda.is_available() else "cpu",
        progress=False,
        eval_every=0,
        checkpoint_every=0,
        fused_loss=not args.reference_loss,
    )
    trainer = Trainer(config)
    trainer._setup()
    generator = torch.Generator(device=trainer.device).manual_seed(0)
    source = GaussianModel.from_ply(read_ply(args.ply), device=trainer.device) if args.ply else trainer.model
    trainer.model = resampled(source, count, generator)
    trainer.optimizer = make_optimizer(trainer.model, trainer.config.lr, trainer.scene.extent)
    trainer.strategy_state = trainer.strategy.initialize_state(trainer.model)
    trainer.step = args.at - 1
    return trainer


def instrument(trainer: Trainer) -> None:
    """Wrap each part of ``train_step`` in a labelled range (the trainer's own objects only)."""
    trainer._next_view = labelled("view and learning rate", trainer._next_view)
    trainer._render = labelled("render forward", trainer._render)
    strategy, optimizer, guard = trainer.strategy, trainer.optimizer, trainer.guard
    for name, label in (
        ("before_backward", "strategy before backward"),
        ("observe", "strategy observe"),
        ("after_step", "strategy after step"),
    ):
        object.__setattr__(strategy, name, labelled(label, getattr(strategy, name)))
    optimizer.step = labelled("optimizer step", optimizer.step)
    optimizer.zero_grad = labelled("zero grad", optimizer.zero_grad)
    guard.record = labelled("guard", guard.record)


def measure(args, count: int) -> dict:
    with tempfile.TemporaryDirectory() as out:
        trainer = prepared(args, count, out)
        device = trainer.device
        sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
        at = trainer.step
        for _ in range(args.warmup):
            trainer.train_step()
        trainer.step = at  # the window sits at --at, not after the warm-up
        sync()
        start = time.perf_counter()
        for _ in range(args.steps):
            trainer.train_step()
        sync()
        wall_ms = (time.perf_counter() - start) * 1e3 / args.steps
        trainer.step = at
        instrument(trainer)
        real_loss = {name: getattr(trainer_module, name) for name in ("fused_photometric_loss", "photometric_loss")}
        real_backward = torch.Tensor.backward
        for name, fn in real_loss.items():
            setattr(trainer_module, name, labelled("loss forward", fn))
        torch.Tensor.backward = labelled("backward", real_backward)
        try:
            from torch.profiler import ProfilerActivity, profile

            activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=activities) as prof:
                for _ in range(args.steps):
                    trainer.train_step()
                sync()
        finally:
            torch.Tensor.backward = real_backward
            for name, fn in real_loss.items():
                setattr(trainer_module, name, fn)
        _, _, info = trainer._render(0)
        row = summarise(prof, args.steps, wall_ms, trainer.model.num, info.num_intersections)
        if args.complexity_views:
            row["complexity_pass"] = complexity_pass(trainer, args.complexity_views)
        return row


def complexity_pass(trainer: Trainer, views: int) -> dict:
    """CDC-GS's Γ over ``views`` training views (what the full schedule runs over every view at each
    densification step): wall ms per view, and the profile of one pass."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    from cdcgs.complexity import ComplexityMaps, complexity_over_views

    device = trainer.device
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    maps = ComplexityMaps(trainer.scene.train[:views], "dwt", device)
    maps.all()
    complexity_over_views(trainer._bins, maps, trainer.model.num, device)  # warm-up
    sync()
    start = time.perf_counter()
    complexity_over_views(trainer._bins, maps, trainer.model.num, device)
    sync()
    wall_ms = (time.perf_counter() - start) * 1e3 / views
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        complexity_over_views(trainer._bins, maps, trainer.model.num, device)
        sync()
    kernels: dict[str, float] = {}
    for e in prof.events():
        if e.device_type == DeviceType.CUDA and not _annotation(e):
            kernels[e.name] = kernels.get(e.name, 0.0) + e.time_range.elapsed_us() / 1e3 / views
    top = dict(sorted(kernels.items(), key=lambda kv: -kv[1])[:12])
    return {
        "views": views,
        "wall_ms_per_view": wall_ms,
        "kernel_ms_per_view": sum(kernels.values()),
        "top_kernels": top,
    }


def _annotation(event) -> bool:
    return bool(getattr(event, "is_user_annotation", False)) or event.name in PARTS or "#" in event.name


def summarise(prof, steps: int, wall_ms: float, gaussians: int, intersections: int) -> dict:
    from torch.autograd import DeviceType

    events = prof.events()
    # The device rows also hold the labelled ranges as GPU-side spans (user annotations: the
    # parts, torch's own "Optimizer.step#..."): they are not kernels.
    device = [e for e in events if e.device_type == DeviceType.CUDA and not _annotation(e)]
    kernels = [e for e in device if not e.name.startswith("Memcpy")]
    copies = [e for e in device if e.name.startswith("Memcpy")]
    stages: dict[str, float] = {}
    by_name: dict[str, list] = {}
    for e in kernels:
        stage = stage_of(e.name)
        ms = e.time_range.elapsed_us() / 1e3 / steps
        stages[stage] = stages.get(stage, 0.0) + ms
        entry = by_name.setdefault(e.name, [0.0, 0.0])
        entry[0] += ms
        entry[1] += 1.0 / steps
    top = sorted(by_name.items(), key=lambda kv: -kv[1][0])[:25]
    # The GPU busy share: the union of the kernel and copy intervals over the window they span.
    intervals = sorted((e.time_range.start, e.time_range.end) for e in kernels + copies)
    busy, span = 0.0, 0.0
    if intervals:
        current_start, current_end = intervals[0]
        for s, e in intervals[1:]:
            if s > current_end:
                busy += current_end - current_start
                current_start, current_end = s, e
            else:
                current_end = max(current_end, e)
        busy += current_end - current_start
        span = intervals[-1][1] - intervals[0][0]
    parts = {}
    for row in prof.key_averages():
        if row.key in PARTS:
            parts[row.key] = {
                "host_ms": row.cpu_time_total / 1e3 / steps,
                "gpu_ms": getattr(row, "device_time_total", getattr(row, "cuda_time_total", 0.0)) / 1e3 / steps,
            }
    cpu_names = [e.name for e in events if e.device_type == DeviceType.CPU]
    warp = sum(1 for e in kernels if "_cuda_kernel_" in e.name)
    return {
        "gaussians": gaussians,
        "intersections": intersections,
        "wall_ms_per_step": wall_ms,
        "profiled_ms_per_step": span / 1e3 / steps if span else None,
        "gpu_busy_share": busy / span if span else None,
        "kernel_ms_per_step": sum(stages.values()),
        "kernels_per_step": len(kernels) / steps,
        "warp_kernels_per_step": warp / steps,
        "torch_kernels_per_step": (len(kernels) - warp) / steps,
        "syncs_per_step": sum(cpu_names.count(n) for n in SYNC_CALLS) / steps,
        "item_calls_per_step": cpu_names.count("aten::_local_scalar_dense") / steps,
        "device_to_host_copies_per_step": sum(1 for e in copies if "DtoH" in e.name) / steps,
        "host_to_device_copies_per_step": sum(1 for e in copies if "HtoD" in e.name) / steps,
        "stages_gpu_ms": stages,
        "top_kernels": [
            {"name": name[:160], "ms_per_step": ms, "launches_per_step": count} for name, (ms, count) in top
        ],
        "parts": parts,
    }


def print_report(rows: list[dict], machine: str) -> None:
    print(f"\n{machine}, cdcgs {cdcgs.__version__}")
    header = "| | " + " | ".join(f"{r['gaussians'] / 1e6:.2f}M" for r in rows) + " |"
    print(header + "\n|---|" + "---|" * len(rows))

    def line(label, values):
        print(f"| {label} | " + " | ".join(values) + " |")

    line("tile intersections (view 0)", [f"{r['intersections']:,}" for r in rows])
    line("ms per step (wall)", [f"{r['wall_ms_per_step']:.2f}" for r in rows])
    line("GPU busy", [f"{100 * (r['gpu_busy_share'] or 0):.0f}%" for r in rows])
    line("kernel time (ms)", [f"{r['kernel_ms_per_step']:.2f}" for r in rows])
    line(
        "kernels: Warp / torch", [f"{r['warp_kernels_per_step']:.1f} / {r['torch_kernels_per_step']:.1f}" for r in rows]
    )
    line(
        "syncs / .item() / D2H copies",
        [
            f"{r['syncs_per_step']:.1f} / {r['item_calls_per_step']:.1f} / {r['device_to_host_copies_per_step']:.1f}"
            for r in rows
        ],
    )
    for stage in [s for s, _ in STAGES] + ["other (torch)"]:
        line(f"GPU: {stage}", [f"{r['stages_gpu_ms'].get(stage, 0.0):.3f}" for r in rows])
    if all("complexity_pass" in r for r in rows):
        line("Γ pass: ms per view (wall)", [f"{r['complexity_pass']['wall_ms_per_view']:.2f}" for r in rows])
        line("Γ pass: kernel ms per view", [f"{r['complexity_pass']['kernel_ms_per_view']:.2f}" for r in rows])
    for part in PARTS:
        line(
            f"host / GPU: {part}",
            [
                f"{r['parts'].get(part, {}).get('host_ms', 0.0):.2f} / {r['parts'].get(part, {}).get('gpu_ms', 0.0):.2f}"
                for r in rows
            ],
        )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="scene folder (COLMAP)")
    parser.add_argument("--images", default=None, help="image folder of the scene, e.g. images")
    parser.add_argument("--ply", default=None, help="a trained model to start from (else the scene's points)")
    parser.add_argument("--gaussians", type=int, nargs="+", default=[1_000_000, 3_000_000])
    parser.add_argument("--strategy", default="3dgs")
    parser.add_argument("--at", type=int, default=20_000, help="iteration counter of the window")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--reference-loss", action="store_true", help="kornia's SSIM and torch's L1")
    parser.add_argument(
        "--rectangles", action="store_true", help="bin each Gaussian into its whole rectangle (no exact footprints)"
    )
    parser.add_argument(
        "--complexity-views", type=int, default=0, help="also time CDC-GS's Γ pass over this many views (0: no)"
    )
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    if not os.path.isdir(args.data):
        parser.error(f"--data {args.data!r} is not a folder")
    if args.ply and not os.path.isfile(args.ply):
        parser.error(f"--ply {args.ply!r} is not a file")
    import cdcgs.render

    exact = cdcgs.render.bin_gaussians

    def rectangles(*a, conics=None, opacities=None, **k):
        return exact(*a, **k)

    if args.rectangles:
        cdcgs.render.bin_gaussians = rectangles
    try:
        rows = [measure(args, count) for count in args.gaussians]
    finally:
        cdcgs.render.bin_gaussians = exact
    machine = torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu"
    print_report(rows, machine)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": machine, "args": vars(args), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
