"""Where the steps of a real training go, on every process: a torch.profiler window inside
``cdcgs train``, on one process, under data parallelism or on shards.

    python benchmarks/profile_training.py [--from 4000] [--steps 100] [--out profile.json] -- TRAIN OPTIONS
    torchrun --standalone --nproc_per_node=2 benchmarks/profile_training.py --from 2000 --steps 100 \\
        --out profile.json -- --data SCENE --images images --batch-size 2 --dist-mode shards ...

``TRAIN OPTIONS`` are ``cdcgs train``'s, taken as the command takes them (the steps replayed as CUDA
graphs where the training replays them: the window is a callback, which no training refuses).
After the step that reaches iteration ``--from``, every process waits for its device, starts the
wall clock and torch.profiler (CUDA's kernels: CUPTI sees Warp's, torch's and NCCL's, those of
replayed graphs included), and ``--steps`` optimizer steps later waits for the device again and
stops both.
Each process summarises its window as ``benchmarks/profile_step.py`` summarises a step's profile:
wall milliseconds per step, the share of the window its GPU is busy (the union of the kernels'
intervals: NCCL's kernels run on a stream of their own, beside the others, and a kernel of theirs
that waits for the other GPU counts as busy: its stage's time holds the wait), GPU milliseconds per
step by stage (``benchmarks/run.py``'s stages, NCCL's kernels one of them) and the kernels that
take the most. Rank 0 prints every process's figures side by side and writes ``--out`` (JSON). The
profiler slows the host: compare GPU times, and the busy share, rather than the wall clock.

A window that a densification step, an evaluation, a checkpoint or a timed step of several
processes (one in 250, eager, each exchange waited for) falls into holds their work too; choose
``--from`` past the densification (``--densify-until``) for the steady state. Steps taken again
after a render overflowed its slots (``--sync-free``, the replayed steps) are counted as they are
taken: the report gives the window's rewinds. Only a training that reaches its end reports (a
failed one stops its profiler and leaves the others to the training's own error).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

from profile_step import summarise
from run import STAGES

from cdcgs import cli
from cdcgs.errors import InputError, OptionError


class ProfileWindow:
    """The trainer's callback that profiles ``steps`` optimizer steps from iteration ``first`` on
    (every process at the same iterations) and keeps every process's summary (``reports``)."""

    def __init__(self, first: int, steps: int):
        self.first, self.steps = first, steps
        self._profiler = None
        self._started_at = 0.0
        self._steps_in = 0
        self.reports: list[dict] | None = None

    def on_start(self, trainer) -> None:
        pass

    def on_step(self, trainer) -> None:
        if self.reports is not None:
            return
        if self._profiler is None:
            if trainer.step >= self.first:
                self._start(trainer)
            return
        self._steps_in += 1
        if self._steps_in >= self.steps:
            self._stop(trainer)

    def on_end(self, trainer) -> None:
        if self._profiler is None or self.reports is not None:
            return
        if self._steps_in and trainer.step >= trainer.config.iters:
            self._stop(trainer)  # the training ended inside the window: what it held
        else:  # no step in the window, or a training that failed: no collective with the others
            self._profiler.__exit__(None, None, None)
            self._profiler = None

    def _start(self, trainer) -> None:
        from torch.profiler import ProfilerActivity, profile

        cuda = trainer.device.type == "cuda"
        if cuda:
            torch.cuda.synchronize(trainer.device)
        self._profiler = profile(activities=[ProfilerActivity.CUDA] if cuda else [ProfilerActivity.CPU])
        self._profiler.__enter__()
        self._started_at = time.perf_counter()
        self._first_step = trainer.step
        self._rewinds = self._rewinds_of(trainer)

    @staticmethod
    def _rewinds_of(trainer) -> int:
        return trainer.lookahead.rewinds if trainer.lookahead is not None else 0

    def _stop(self, trainer) -> None:
        if trainer.device.type == "cuda":
            torch.cuda.synchronize(trainer.device)
        wall_ms = (time.perf_counter() - self._started_at) * 1e3 / self._steps_in
        self._profiler.__exit__(None, None, None)
        mine = summarise(self._profiler, self._steps_in, wall_ms, {}, trainer.num_gaussians, 0)
        mine.update(
            rank=trainer.ranks.rank,
            steps=self._steps_in,
            iterations=[self._first_step + 1, trainer.step],
            rewinds=self._rewinds_of(trainer) - self._rewinds,
            device=torch.cuda.get_device_name(trainer.device) if trainer.device.type == "cuda" else "cpu",
        )
        self._profiler = None
        self.reports = trainer.ranks.all_gather_object(mine)  # every process stops at the same step


def table(reports: list[dict]) -> str:
    """Every process's figures side by side (markdown)."""
    heads = " | ".join(f"rank {r['rank']}" for r in reports)
    lines = [
        f"{reports[0]['steps']} steps, iterations {reports[0]['iterations'][0]}–{reports[0]['iterations'][1]}, "
        f"{reports[0]['gaussians']:,} Gaussians, on {reports[0]['device']}:",
        "",
        f"| per step | {heads} |",
        "|---|" + "---:|" * len(reports),
    ]

    def row(label: str, values) -> None:
        lines.append(f"| {label} | " + " | ".join(values) + " |")

    if any(r["rewinds"] for r in reports):
        lines[0] += f" ({reports[0]['rewinds']} rewinds in the window: steps taken again are counted twice)"
    row("wall (ms, profiled)", [f"{r['wall_ms_per_step']:.2f}" for r in reports])
    row("GPU busy", [f"{100 * r['gpu_busy_share']:.0f}%" if r["gpu_busy_share"] else "—" for r in reports])
    row("kernels (ms)", [f"{r['kernel_ms_per_step']:.2f}" for r in reports])
    for stage in [s for s, _ in STAGES] + ["other (torch)"]:
        if any(stage in r["stages_gpu_ms"] for r in reports):
            row(f"  {stage}", [f"{r['stages_gpu_ms'].get(stage, 0.0):.3f}" for r in reports])
    lines += ["", "Kernels that take the most (rank 0):", ""]
    for kernel in reports[0]["top_kernels"][:12]:
        lines.append(f"- {kernel['ms_per_step']:.3f} ms, {kernel['launches_per_step']:.1f}× — {kernel['name'][:100]}")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    mine, train = (argv[: argv.index("--")], argv[argv.index("--") + 1 :]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--from",
        dest="first",
        type=int,
        default=4000,
        help="the window starts after the step that reaches this iteration",
    )
    parser.add_argument("--steps", type=int, default=100, help="optimizer steps in the window")
    parser.add_argument("--out", default=None, help="JSON file of every process's figures (rank 0 writes it)")
    args = parser.parse_args(mine)
    if args.first < 0 or args.steps < 1:
        parser.error(f"--from must be 0 or more and --steps positive, got {args.first} and {args.steps}")
    if not train:
        parser.error("give cdcgs train's options after --, e.g. -- --data SCENE")
    cli.ask_for_expandable_segments()
    train_args = cli.build_parser().parse_args(["train", *train])
    window = ProfileWindow(args.first, args.steps)
    try:
        code = cli.cmd_train(train_args, callbacks=[window])
    except (InputError, OptionError) as err:  # as cdcgs train says them: a path or an option named
        print(f"profile_training: {err}", file=sys.stderr)
        return 2
    if code != 0:
        return code
    if window.reports is None:
        print(f"profile_training: the training ended before iteration {args.first}: nothing profiled", file=sys.stderr)
        return 1
    if os.environ.get("RANK", "0") in ("", "0"):
        print(table(window.reports))
        if args.out:
            report = {"date": datetime.date.today().isoformat(), "train_options": train, "ranks": window.reports}
            with open(args.out, "w") as f:
                json.dump(report, f, indent=1)
    return 0


if __name__ == "__main__":
    cli.exit_process(main())
