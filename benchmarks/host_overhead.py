"""The host's share of a training step: Python, argument checks, Warp's launch packing, torch's
dispatch and autograd, measured where the kernels cost next to nothing.

    python benchmarks/host_overhead.py [--data SCENE] [--gaussians 200] [--size 32 24] [--steps 1000]
        [--top 25] [--profile-out step.prof]

The trainer is set up as ``cdcgs train`` does (benchmarks/profile_step.py's set-up: the scene's
points resampled to ``--gaussians``, the iteration counter at ``--at``), on a tiny scene: without
``--data`` a procedural one of 8 views of ``--size`` pixels, written to a temporary folder. On the
CPU, Warp runs its kernels inside ``wp.launch``: their time is measured and left out, and what
remains of the wall time of ``Trainer.train_step`` is the host's work (torch's CPU kernels on
tensors this small take microseconds). On CUDA nothing is synchronised inside the timed steps, so
they time the host side too, except where the render reads its intersection count and waits for
the device (a part of its own in the table).

Printed: host ms per step, the median over ``--steps`` steps of each step's time less that of the
Warp kernels that ran on the CPU in it; the host time of each part of the step (profile_step's
clock: ``time.perf_counter`` around each, less the parts inside it) over as many steps more; then
as many under cProfile: the ``--top`` functions by own time and by cumulative time, in
microseconds per step (cProfile's own cost inflates these; compare them with each other).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import os
import pstats
import statistics
import sys
import tempfile
import time

import torch
import warp._src.context as warp_context

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from profile_step import PARTS, PartClock, instrumented, prepared

from cdcgs.cli import ask_for_expandable_segments
from cdcgs.datasets.procedural import make_procedural_scene

KERNELS = "Warp kernels, sorts and scans running on the CPU"


@contextlib.contextmanager
def cpu_kernels_timed(clock: PartClock):
    """On the CPU, Warp runs a kernel inside ``wp.launch`` (its ``invoke``: the argument struct
    and the native call), and a radix sort or a scan in a native call: device work on a GPU, timed
    here as a part of its own, which the other parts then leave out. Warp's private functions
    (1.19), patched for the duration; on CUDA they are not called."""
    core = warp_context.runtime.core
    natives = [name for name in dir(core) if name.startswith(("wp_radix_sort_pairs_", "wp_array_scan_"))]
    real = [(warp_context, name, getattr(warp_context, name)) for name in ("invoke", "invoke_cpu_blocks")]
    real += [(core, name, getattr(core, name)) for name in natives if name.endswith("_host")]
    for owner, name, fn in real:
        setattr(owner, name, clock.wrap(KERNELS, fn))
    try:
        yield clock
    finally:
        for owner, name, fn in real:
            setattr(owner, name, fn)


def host_times(trainer, steps: int) -> list[float]:
    """Each step's ms less the Warp kernels that ran on the CPU in it, over ``steps`` steps from the
    same iteration; no synchronisation. One by one, so that the median leaves out the steps that
    another process slowed down."""
    at, times = trainer.step, []
    with cpu_kernels_timed(PartClock()) as clock:
        for _ in range(steps):
            kernels = clock.seconds.get(KERNELS, 0.0)
            start = time.perf_counter()
            trainer.train_step()
            elapsed = time.perf_counter() - start
            times.append((elapsed - (clock.seconds.get(KERNELS, 0.0) - kernels)) * 1e3)
    trainer.step = at
    return times


def timed_window(trainer, steps: int) -> float:
    """ms per step over ``steps`` steps from the same iteration; no synchronisation inside."""
    at = trainer.step
    start = time.perf_counter()
    for _ in range(steps):
        trainer.train_step()
    elapsed = time.perf_counter() - start
    trainer.step = at
    return elapsed * 1e3 / steps


def short_path(path: str) -> str:
    """A source file's path from the repository root or from its site-packages folder."""
    root = os.path.dirname(HERE)
    if path.startswith(root + os.sep):
        return os.path.relpath(path, root)
    return path.rpartition("site-packages" + os.sep)[2] or path


def top_functions(profile: cProfile.Profile, steps: int, key: str, count: int) -> list[tuple[str, float, float, float]]:
    """(function, calls per step, own us per step, cumulative us per step), ``key`` first."""
    rows = []
    for (path, line, name), (_, calls, own, cumulative, _) in pstats.Stats(profile).stats.items():
        where = name if path == "~" else f"{short_path(path)}:{line} {name}"
        rows.append((where, calls / steps, own * 1e6 / steps, cumulative * 1e6 / steps))
    index = {"own": 2, "cumulative": 3}[key]
    return sorted(rows, key=lambda row: -row[index])[:count]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=None, help="scene folder (default: a tiny procedural scene)")
    parser.add_argument("--images", default=None)
    parser.add_argument("--ply", default=None, help="a trained model to start from (else the scene's points)")
    parser.add_argument("--gaussians", type=int, default=200)
    parser.add_argument("--size", type=int, nargs=2, default=(32, 24), help="width and height of the procedural scene")
    parser.add_argument("--strategy", default="3dgs")
    parser.add_argument(
        "--at", type=int, default=20_000, help="iteration counter of the window (20000: no densification)"
    )
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--reference-loss", action="store_true", help="kornia's SSIM and torch's L1")
    parser.add_argument(
        "--torch-adam", action="store_true", help="torch's fused Adam (one launch per group) instead of FusedAdam"
    )
    parser.add_argument("--profile-out", default=None, help="also write the cProfile window's stats here")
    args = parser.parse_args(argv)
    ask_for_expandable_segments()  # before CUDA allocates: as `cdcgs train` runs
    # One intra-op thread: torch's parallel regions on a busy 2-core machine cost milliseconds
    # (OpenMP waiting for its second thread), which is not the overhead a GPU's host pays.
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as folder:
        if args.data is None:
            args.data = make_procedural_scene(
                os.path.join(folder, "scene"), views=8, width=args.size[0], height=args.size[1], points=300
            )
        trainer = prepared(args, args.gaussians, os.path.join(folder, "run"))
        timed_window(trainer, args.warmup)
        steps_ms = host_times(trainer, args.steps)
        with instrumented(trainer, PartClock()) as clock, cpu_kernels_timed(clock):
            instrumented_ms = timed_window(trainer, args.steps)
        profile = cProfile.Profile()
        profile.enable()
        timed_window(trainer, args.steps)
        profile.disable()
    if args.profile_out:
        profile.dump_stats(args.profile_out)
    device = torch.cuda.get_device_name(trainer.device) if trainer.device.type == "cuda" else "cpu"
    view = trainer.scene.train[0]
    deciles = statistics.quantiles(steps_ms, n=10)
    parts = {part: clock.seconds.get(part, 0.0) * 1e3 / args.steps for part in [*PARTS, KERNELS]}
    parts["rest of the step"] = max(instrumented_ms - sum(parts.values()), 0.0)
    print(f"\n{device}, {trainer.model.num} Gaussians, {view.width} x {view.height} pixels")
    print(
        f"host ms per step: {statistics.median(steps_ms):.3f} (median of {args.steps} steps; deciles 1 and 9: "
        f"{deciles[0]:.3f}, {deciles[-1]:.3f}), each step's time less the {KERNELS}"
    )
    print(f"\n| part (a window timed by parts: {instrumented_ms:.3f} ms per step) | host ms per step |\n|---|---|")
    for part, ms in parts.items():
        print(f"| {part} | {ms:.3f} |")
    for key in ("own", "cumulative"):
        print(f"\n| function (cProfile, by {key} time) | calls per step | own us | cumulative us |\n|---|---|---|---|")
        for where, calls, own, cumulative in top_functions(profile, args.steps, key, args.top):
            print(f"| {where} | {calls:.1f} | {own:.1f} | {cumulative:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
