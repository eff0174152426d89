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
synchronisation at both ends only: the step as the training runs it), plainly and then with a clock
around each part, then the same number under torch.profiler (CUPTI sees Warp's kernels as well as
torch's). Each part of ``Trainer.train_step`` is wrapped: a ``time.perf_counter`` clock during the
wall-clock window (no synchronisation: the host time of the part, less the parts inside it) and a
labelled range under the profiler (the GPU time of the kernels it launched). The render's read of
its intersection count, where the host waits for the device, is a part of its own, so that "render
forward" is the host's work alone.

Printed and written to ``--out``: ms per step (wall) with the part clocks and without them (the
plain step, timed first), the share of the profiled window the GPU is busy (the union of kernel
intervals; the profiler slows the host, so this share is low) and the kernel time over the plain
step (the busy share of the step as training runs it: one stream runs the kernels in turn), kernels
per step (Warp's and torch's), host synchronisations and device-to-host copies per step, GPU time
per stage (by kernel name) and, per part of the step, host time and the GPU time of the kernels it
launched; "rest of the step" is the wall time less the parts' host time: the trainer's own code, and
where the GPU sets the pace, the wait for it at the window's end.

``--cuda-graph``: the step of ``cdcgs train --cuda-graph``, set up as ``--sync-free``'s; the
replayed steps call none of the wrapped parts, so the plain step and the kernels are its figures.

``--sync-free``: the step of ``cdcgs train --sync-free``. Every training view is rendered once
before the windows, so that each view's count is known and every render in them goes into slots;
each window ends with the one read of the device flags that a training makes every 50 iterations
("sync-free read"), and the row records how many renders read their count and how many halted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import tempfile
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from kernel_options import add_kernel_options, check_kernel_options, kernel_options
from run import STAGES, stage_of

import cdcgs
import cdcgs.render
from cdcgs.cli import ask_for_expandable_segments
from cdcgs.io import read_ply
from cdcgs.train import trainer as trainer_module
from cdcgs.train.config import DataConfig, TrainConfig
from cdcgs.train.mcmc import MCMC
from cdcgs.train.model import GaussianModel
from cdcgs.train.ops import make_optimizer, morton_order
from cdcgs.train.strategies import strategy_class
from cdcgs.train.trainer import Trainer

# The parts of a step, in the order they run; each is a labelled range in the profile.
PASS_REPEATS = 3  # passes of each way of the Γ pass, in turn

PARTS = [
    "view and learning rate",
    "render forward",
    "intersection count (sync)",
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


class PartClock:
    """Host seconds per part of the step: ``time.perf_counter`` around each call of a wrapped
    function, less the time of the wrapped calls inside it (the count read inside the render), with
    no device synchronisation. ``profiling``: also open a labelled range for torch.profiler (off in
    the wall-clock window, where the range itself would cost host time)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.profiling = False
        self._inner: list[float] = []  # per open call: the seconds of the wrapped calls inside it

    def wrap(self, label: str, fn):
        def wrapped(*args, **kwargs):
            self._inner.append(0.0)
            start = time.perf_counter()
            try:
                if self.profiling:
                    with torch.profiler.record_function(label):
                        return fn(*args, **kwargs)
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - start
                self.seconds[label] = self.seconds.get(label, 0.0) + elapsed - self._inner.pop()
                if self._inner:
                    self._inner[-1] += elapsed

        return wrapped


def resampled(model: GaussianModel, count: int, generator: torch.Generator, order: str = "drawn") -> GaussianModel:
    """``count`` Gaussians from ``model``: a random subset (in the order drawn, or with ``order``
    "kept" in the model's own), or every one plus copies moved by a draw of their own scale (as a
    split would place them), appended; with ``order`` "morton" sorted by the Morton code of their
    means (neighbours in space neighbours in memory, as Faster-GS orders them)."""
    params = {k: v.detach() for k, v in model.params.items()}
    n = params["means"].shape[0]
    device = params["means"].device
    if count <= n:
        keep = torch.randperm(n, generator=generator, device=device)[:count]
        if order == "kept":
            keep = keep.sort().values
        params = {k: v[keep] for k, v in params.items()}
    else:
        extra = torch.randint(0, n, (count - n,), generator=generator, device=device)
        copies = {k: v[extra].clone() for k, v in params.items()}
        jitter = torch.randn(count - n, 3, generator=generator, device=device)
        copies["means"] += jitter * params["log_scales"][extra].exp()
        params = {k: torch.cat([v, copies[k]]) for k, v in params.items()}
    if order == "morton":
        permutation = morton_order(params["means"])
        params = {k: v[permutation] for k, v in params.items()}
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
        sync_free=getattr(args, "sync_free", False),  # host_overhead.py shares this set-up
        cuda_graph=getattr(args, "cuda_graph", False),
    )
    options = {}
    if issubclass(strategy_class(args.strategy), MCMC):  # its budget: the profiled count
        options["target_gaussians"] = count
    trainer = Trainer(config, strategy_options=options)
    trainer._setup()
    generator = torch.Generator(device=trainer.device).manual_seed(0)
    source = GaussianModel.from_ply(read_ply(args.ply), device=trainer.device) if args.ply else trainer.model
    trainer.model = resampled(source, count, generator, getattr(args, "order", "drawn"))
    if args.torch_adam and trainer.config.optimizer == "selective":
        raise SystemExit(f"--torch-adam: the {args.strategy} preset trains with selective Adam, which torch has not")
    # --torch-adam: the optimizer before FusedAdam, torch's fused Adam (one launch per group)
    kind = "torch-adam" if args.torch_adam else "adam"
    trainer.optimizer = make_optimizer(trainer.model, trainer.config.lr, trainer.scene.extent, kind)
    trainer.strategy_state = trainer.strategy.initialize_state(trainer.model)
    trainer.step = args.at - 1
    if trainer.lookahead is not None:  # every view's count known: the windows render into slots only
        with torch.no_grad():
            for view in range(len(trainer.scene.train)):
                count = trainer._render(view)[2].num_intersections
                trainer.lookahead.counted(view, count, trainer.model.num)
        trainer.lookahead.renders = {"counted": 0, "within": 0}
    return trainer


def settle(trainer: Trainer) -> None:
    """--sync-free: the read at a window's end (a halt goes back, and the window is timed anyway;
    the row's ``sync_free`` counts the halts, and a window with one is flagged when printed)."""
    if trainer.lookahead is not None:
        trainer._settle()


def step(trainer: Trainer) -> None:
    """One ``train_step``; with --sync-free one that a read inside it (before a refinement) ended
    by going back counts as taken (the window's time holds it, and its halt is counted)."""
    with contextlib.suppress(trainer_module._Rewound):
        trainer.train_step()


@contextlib.contextmanager
def instrumented(trainer: Trainer, clock: PartClock):
    """Wrap each part of ``train_step`` in ``clock`` for the duration: methods of the trainer's own
    objects, the loss functions it calls, ``torch.Tensor.backward`` and the render's count reader."""
    strategy, optimizer, guard = trainer.strategy, trainer.optimizer, trainer.guard
    methods = [
        (trainer, "_next_view", "view and learning rate"),
        (trainer, "_render", "render forward"),
        (strategy, "before_backward", "strategy before backward"),
        (strategy, "observe", "strategy observe"),
        (strategy, "after_step", "strategy after step"),
        (optimizer, "step", "optimizer step"),
        (optimizer, "zero_grad", "zero grad"),
        (guard, "record", "guard"),
        (trainer, "_settle", "sync-free read"),
    ]
    loss_functions = {name: getattr(trainer_module, name) for name in ("fused_photometric_loss", "photometric_loss")}
    real_backward, real_reader = torch.Tensor.backward, cdcgs.render._count_reader

    def count_reader(*args, **kwargs):
        return clock.wrap("intersection count (sync)", real_reader(*args, **kwargs))

    own = [(owner, name, getattr(owner, "__dict__", {}).get(name)) for owner, name, _ in methods]  # instance attributes
    for owner, name, label in methods:  # object.__setattr__: strategies may be frozen dataclasses
        object.__setattr__(owner, name, clock.wrap(label, getattr(owner, name)))
    for name, fn in loss_functions.items():
        setattr(trainer_module, name, clock.wrap("loss forward", fn))
    torch.Tensor.backward = clock.wrap("backward", real_backward)
    cdcgs.render._count_reader = count_reader
    try:
        yield clock
    finally:
        torch.Tensor.backward, cdcgs.render._count_reader = real_backward, real_reader
        for name, fn in loss_functions.items():
            setattr(trainer_module, name, fn)
        for owner, name, before in own:  # the instance's own attribute back, or the class's method
            if before is None:
                object.__delattr__(owner, name)
            else:
                object.__setattr__(owner, name, before)


def measure(args, count: int) -> dict:
    from torch.profiler import ProfilerActivity, profile

    with tempfile.TemporaryDirectory() as out:
        trainer = prepared(args, count, out)
        device = trainer.device
        sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
        at = trainer.step
        for _ in range(args.warmup):
            step(trainer)
        settle(trainer)
        trainer.step = at  # the window sits at --at, not after the warm-up
        sync()
        start = time.perf_counter()
        for _ in range(args.steps):  # the plain step: no part clocks, no profiler
            step(trainer)
        settle(trainer)
        sync()
        plain_ms = (time.perf_counter() - start) * 1e3 / args.steps
        trainer.step = at
        with instrumented(trainer, PartClock()) as clock:
            sync()
            start = time.perf_counter()
            for _ in range(args.steps):
                step(trainer)
            settle(trainer)
            sync()
            wall_ms = (time.perf_counter() - start) * 1e3 / args.steps
            host_ms = {part: seconds * 1e3 / args.steps for part, seconds in clock.seconds.items()}
            trainer.step = at
            clock.profiling = True
            activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=activities) as prof:
                for _ in range(args.steps):
                    step(trainer)
                settle(trainer)
                sync()
        _, _, info = trainer._render(0)
        row = summarise(prof, args.steps, wall_ms, host_ms, trainer.model.num, info.num_intersections)
        row["plain_ms_per_step"] = plain_ms
        if trainer.lookahead is not None:
            row["sync_free"] = trainer.lookahead.summary()
        if trainer.graphs is not None:
            row["cuda_graph"] = trainer.graphs.summary()
        # One stream runs the kernels one after another: their sum over the plain step's time is
        # the GPU's busy share when nothing measures the host.
        row["kernel_share_of_plain_step"] = min(row["kernel_ms_per_step"] / plain_ms, 1.0)
        if args.complexity_views:
            row["complexity_pass"] = complexity_pass(trainer, args.complexity_views)
        return row


def complexity_pass(trainer: Trainer, views: int) -> dict:
    """CDC-GS's Γ over ``views`` training views (what the full schedule runs over every view at each
    densification step): wall ms per view as the trainer runs it (the next view queued before this
    one's count is read) and one view at a time (``wall_ms_per_view_one_at_a_time``, each view's
    lists finished before the next starts), each the median of PASS_REPEATS passes taken in turn,
    and the profile of one pass."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    from cdcgs.complexity import ComplexityMaps, complexity_over_views

    device = trainer.device
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    maps = ComplexityMaps(trainer.scene.train[:views], "dwt", device)
    maps.all()
    ways = {"pipelined": trainer._bins, "one at a time": lambda i, counted=False: _finished(trainer._bins(i, counted))}
    for bins in ways.values():  # warm-up
        complexity_over_views(bins, maps, trainer.model.num, device)
    sync()
    times: dict[str, list[float]] = {way: [] for way in ways}
    for _ in range(PASS_REPEATS):  # the two ways in turn, so that neither gets the quieter moments
        for way, bins in ways.items():
            start = time.perf_counter()
            complexity_over_views(bins, maps, trainer.model.num, device)
            sync()
            times[way].append((time.perf_counter() - start) * 1e3 / views)
    wall_ms, one_at_a_time_ms = (statistics.median(times[way]) for way in ways)
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
        "wall_ms_per_view_one_at_a_time": one_at_a_time_ms,
        "kernel_ms_per_view": sum(kernels.values()),
        "top_kernels": top,
    }


def _finished(bins):
    """A view's lists finished: pending ones (``start_bin_view``) waited for; those binned into
    slots (a training that replays its steps) are finished already, so under ``--cuda-graph`` the
    two ways of the Γ pass are the same."""
    return bins.finish() if hasattr(bins, "finish") else bins


def _annotation(event) -> bool:
    return bool(getattr(event, "is_user_annotation", False)) or event.name in PARTS or "#" in event.name


def summarise(prof, steps: int, wall_ms: float, host_ms: dict, gaussians: int, intersections: int) -> dict:
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
    # Host time from the wall-clock window's clock (the profiler's CPU time of a labelled range
    # held only what torch's own ops recorded, 0 for most parts on a GPU); GPU time from the profile.
    parts = {part: {"host_ms": ms, "gpu_ms": 0.0} for part, ms in host_ms.items()}
    for row in prof.key_averages():
        if row.key in parts:
            gpu_us = getattr(row, "device_time_total", getattr(row, "cuda_time_total", 0.0))
            parts[row.key]["gpu_ms"] = gpu_us / 1e3 / steps
    parts["rest of the step"] = {"host_ms": max(wall_ms - sum(host_ms.values()), 0.0), "gpu_ms": 0.0}
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
    line("ms per step, plain (no clocks, no profiler)", [f"{r['plain_ms_per_step']:.2f}" for r in rows])
    line("GPU busy (profiled window)", [f"{100 * (r['gpu_busy_share'] or 0):.0f}%" for r in rows])
    line("kernel time / plain step", [f"{100 * r['kernel_share_of_plain_step']:.0f}%" for r in rows])
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
        line(
            "Γ pass: ms per view (wall), one view at a time",
            [f"{r['complexity_pass']['wall_ms_per_view_one_at_a_time']:.2f}" for r in rows],
        )
        line("Γ pass: kernel ms per view", [f"{r['complexity_pass']['kernel_ms_per_view']:.2f}" for r in rows])
    optional = ["sync-free read"] if any("sync-free read" in r["parts"] for r in rows) else []
    for r in rows:
        if r.get("sync_free", {}).get("rewinds"):
            print(
                f"note: {r['sync_free']['rewinds']} halt(s) in the windows at {r['gaussians']:,}: their steps updated nothing"
            )
    for part in [*PARTS, *optional, "rest of the step"]:
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
    parser.add_argument("--strategy", default="3dgs", help="preset (mcmc ones with the profiled count as budget)")
    parser.add_argument("--at", type=int, default=20_000, help="iteration counter of the window")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--reference-loss", action="store_true", help="kornia's SSIM and torch's L1")
    parser.add_argument(
        "--torch-adam", action="store_true", help="torch's fused Adam (one launch per group) instead of FusedAdam"
    )
    parser.add_argument(
        "--sh-backward",
        choices=("grouped", "staged"),
        default=None,
        help="the SH adjoint's CUDA kernel (cdcgs.render.SH_BACKWARD_CUDA; default: as it is)",
    )
    add_kernel_options(parser)
    parser.add_argument(
        "--rectangles", action="store_true", help="bin each Gaussian into its whole rectangle (no exact footprints)"
    )
    parser.add_argument(
        "--complexity-views", type=int, default=0, help="also time CDC-GS's Γ pass over this many views (0: no)"
    )
    parser.add_argument(
        "--sync-free",
        action="store_true",
        help="the step of cdcgs train --sync-free (renders into slots, no count read)",
    )
    parser.add_argument(
        "--cuda-graph",
        action="store_true",
        help="the step of cdcgs train --cuda-graph (implies --sync-free): replayed steps run no part of the "
        "trainer's Python, so only the plain step's time, the kernels and the host syncs mean something",
    )
    parser.add_argument(
        "--order",
        choices=("drawn", "kept", "morton"),
        default="drawn",
        help="the Gaussians' order in memory: as drawn (random), the model's own, or by Morton code",
    )
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    check_kernel_options(parser, args)
    args.sync_free = args.sync_free or args.cuda_graph
    ask_for_expandable_segments()  # before CUDA allocates: as `cdcgs train` runs
    if not os.path.isdir(args.data):
        parser.error(f"--data {args.data!r} is not a folder")
    if args.ply and not os.path.isfile(args.ply):
        parser.error(f"--ply {args.ply!r} is not a file")
    exact = cdcgs.render.start_binning  # the binning of every render and Γ pass starts here

    def rectangles(*a, conics=None, opacities=None, **k):
        return exact(*a, **k)

    if args.rectangles:
        cdcgs.render.start_binning = rectangles
    sh_backward = cdcgs.render.SH_BACKWARD_CUDA
    cdcgs.render.SH_BACKWARD_CUDA = args.sh_backward or sh_backward
    try:
        with kernel_options(args):
            rows = [measure(args, count) for count in args.gaussians]
    finally:
        cdcgs.render.start_binning = exact
        cdcgs.render.SH_BACKWARD_CUDA = sh_backward
    machine = torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu"
    print_report(rows, machine)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"machine": machine, "args": vars(args), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
