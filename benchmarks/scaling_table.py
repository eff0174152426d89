"""Trainings on 1, 2, 4 ... GPUs with batches of views, one after another, and their scaling table.

    python benchmarks/scaling_table.py --data ../shared/data/bonsai --images images --out runs \
        [--strategies 3dgs cdc] [--configs 1x1 1x2 2x2 4x4] [--iters 30000] [--docs docs/distributed.md]

A config ``GxB`` is G processes (one per GPU, NCCL; ``torchrun --standalone --nproc_per_node=G``
for G > 1) training with ``--batch-size B``; ``--iters`` counts views seen, so every run sees the
same number of images. Each run is its own launch, started after the one before it ended, so that
no two of them share a GPU or the host; what else runs on the machine is watched, not ruled out:
during each timed run nvidia-smi counts the processes on each of its GPUs every few seconds
(``gpu_neighbours.json`` in the run's folder), and the table marks with † a run that shared a GPU
and the speed-ups taken against a baseline that did, and names the runs it could not check. Each
run is preceded by a ``--warmup``-iteration launch of the same
command into a scratch folder (Warp compiles its kernels there, not in the timed run). A config
that needs more GPUs than the machine has is skipped, and said so. ``--side-by-side`` runs the
one-GPU configs at the same time, each on a GPU of its own (``CUDA_VISIBLE_DEVICES``), as many
at once as the machine has GPUs: each is still alone on its GPU, but they share the host (which
slowed them by 3-6% on two H200s). Each strategy's first config, when it is a one-GPU one, is
then trained again alone (folder ``STRATEGY-CONFIG-alone``), and the speed-ups are taken against
that run; the configs of several GPUs run one after another, alone on the machine. The table's
"run" column says how each ran. GPUs only.

The table (steps, training time, images per second and its ratio to the strategy's first config,
test PSNR, SSIM, LPIPS-VGG and -Alex, Gaussians, the largest peak GPU memory of a process, the
all-reduce's share of a step and the wait for the slowest rank before it), with the machine, date
and commit, is printed, written to ``--out``/scaling.md and, with ``--docs``, put into that file
between ``<!-- scaling-table:begin -->`` and ``<!-- scaling-table:end -->``. Runs whose folder already holds a finished run are read, not
trained again (``--retrain`` trains them anew), when they were trained with the same
``--train-option``s (each run records them in ``train_options.json``; a run trained with others is
refused, naming both). ``--device cpu`` runs the same on the CPU (gloo).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shlex
import shutil
import sys
from concurrent.futures import ThreadPoolExecutor

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

from training_table import (
    CPU_RUN,
    NEIGHBOURS,
    _number,
    add_common_arguments,
    check_common_arguments,
    commit,
    gpu_sharing,
    read_run,
    run_watched,
    write_docs,
)

BEGIN, END = "<!-- scaling-table:begin -->", "<!-- scaling-table:end -->"
DEFAULT_CONFIGS = ["1x1", "1x2", "2x2", "4x4"]
# In a run's folder: the --train-options it was trained with, so that a table that reads the run
# again (instead of training it) names what it really ran with.
OPTIONS = "train_options.json"


def parse_config(text: str) -> tuple[int, int]:
    """``GxB`` -> (processes, batch size); ValueError naming the text when it is not one."""
    match = re.fullmatch(r"(\d+)x(\d+)", text)
    if not match or int(match[1]) < 1 or int(match[2]) < int(match[1]):
        raise ValueError(f"{text!r} is not GxB with 1 <= G <= B (G processes, batch B), e.g. 2x2")
    return int(match[1]), int(match[2])


def command(strategy: str, config: str, args, out: str, iters: int) -> list[str]:
    """The command line of one run."""
    processes, batch = parse_config(config)
    train = ["train", "--data", args.data, "--out", out, "--iters", str(iters), "--seed", str(args.seed)]
    if args.images:
        train += ["--images", args.images]
    train += ["--strategy", strategy, "--batch-size", str(batch), "--device", args.device]
    train += ["--no-progress", "--checkpoint-every", "0", "--overwrite", *args.train_options]
    if processes == 1:
        return [sys.executable, "-m", "cdcgs", *train]
    launch = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={processes}"]
    return [*launch, "-m", "cdcgs", *train]


def available_gpus() -> int:
    try:
        import torch

        return torch.cuda.device_count() if torch.cuda.is_available() else 0
    except ImportError:
        return 0


def train(strategy: str, config: str, args, gpu: int | None = None, alone: bool = False) -> dict:
    """Train one run (a warm-up first) and return its metrics.json, or {"skipped": why}.

    ``gpu``: the one GPU the run may see, an index into this process's visible GPUs (its
    ``CUDA_VISIBLE_DEVICES`` narrowed to that one); None leaves the variable as it is. ``alone``:
    the side-by-side mode's baseline, trained into its own folder.
    """
    processes, _ = parse_config(config)
    name = f"{strategy}-{config}" + ("-alone" if alone else "")
    folder = os.path.join(args.out, name)
    metrics_path = os.path.join(folder, "metrics.json")
    if os.path.isfile(metrics_path) and not args.retrain:
        print(f"{name}: read the finished run in {folder}", flush=True)
        return read_finished(folder, args)
    if args.device != "cpu" and processes > available_gpus():
        why = f"needs {processes} GPUs, this machine has {available_gpus()}"
        print(f"{name}: skipped ({why})", flush=True)
        return {"skipped": why}
    scratch = os.path.join(args.out, f".warm-{name}")
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")]))}
    environment.setdefault("CUDA_DEVICE_ORDER", "PCI_BUS_ID")  # CUDA's indices as nvidia-smi's, for the watch
    if gpu is not None:
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        environment["CUDA_VISIBLE_DEVICES"] = visible.split(",")[gpu].strip() if visible else str(gpu)
    steps = [(args.warmup, scratch)] if args.warmup > 0 else []
    seen = CPU_RUN  # on the CPU: nothing to watch
    for iters, out in [*steps, (args.iters, folder)]:
        line = command(strategy, config, args, out, iters)
        where = f" (GPU {environment['CUDA_VISIBLE_DEVICES']})" if gpu is not None else ""
        print(f"{name}{where}: {' '.join(line[1:])}", flush=True)
        limit = args.run_timeout or None
        if out == folder and args.device != "cpu":  # the timed run: is each of its GPUs its own?
            status, seen = run_watched(line, run_gpus(environment, processes), limit=limit, cwd=ROOT, env=environment)
        else:
            status, stopped = run_watched(line, [], limit=limit, cwd=ROOT, env=environment)
            seen = {**seen, **{k: v for k, v in stopped.items() if k == "stopped_after"}}
        if "stopped_after" in seen:
            if out == folder and os.path.isfile(metrics_path):
                # It wrote its results and then did not end (a process that hung at exit): the
                # results stand, the table's note says so.
                print(f"{name}: stopped after {limit:.0f} s; it had written its results but not ended", flush=True)
                continue
            raise SystemExit(f"scaling_table: {name} did not end within --run-timeout {limit:.0f} s; stopped")
        if status != 0:
            raise SystemExit(f"scaling_table: {name} failed (exit status {status}); see its output above")
    shutil.rmtree(scratch, ignore_errors=True)
    with open(os.path.join(folder, NEIGHBOURS), "w") as f:
        json.dump(seen, f)
    with open(os.path.join(folder, OPTIONS), "w") as f:
        json.dump({"train_options": list(args.train_options)}, f)
    return read_finished(folder, args)


def read_finished(folder: str, args) -> dict:
    """A finished run (``read_run``) that was trained with this invocation's ``--train-option``s,
    since the table's heading names them; SystemExit naming both when it was not. A run trained
    before runs recorded their options is read with ``options_unknown`` set (the table says so)."""
    metrics = read_run(folder)
    path = os.path.join(folder, OPTIONS)
    if not os.path.isfile(path):
        metrics["options_unknown"] = True
        return metrics
    try:
        with open(path) as f:
            recorded = json.load(f)["train_options"]
        if not (isinstance(recorded, list) and all(isinstance(o, str) for o in recorded)):
            raise TypeError("not a list of strings")
    except (ValueError, KeyError, TypeError) as error:
        raise SystemExit(
            f"scaling_table: {path} is not a record of --train-options ({error}): pass --retrain, or another --out"
        ) from None
    if recorded != list(args.train_options):

        def shown(options):
            return " ".join(f"--train-option={shlex.quote(o)}" for o in options) or "no --train-option"

        raise SystemExit(
            f"scaling_table: {folder} was trained with {shown(recorded)}, and this table is for "
            f"{shown(args.train_options)}: pass the same, --retrain, or another --out"
        )
    return metrics


def run_gpus(environment: dict, processes: int) -> list[str]:
    """The GPUs (as nvidia-smi names them) of a run of ``processes`` processes, one GPU each: the
    first of its CUDA_VISIBLE_DEVICES, or the first indices where that is not set."""
    visible = [g.strip() for g in environment.get("CUDA_VISIBLE_DEVICES", "").split(",") if g.strip()]
    return (visible or [str(i) for i in range(processes)])[:processes]


Row = tuple[str, str, str]  # (strategy, config, how it ran: "alone" or "side by side")


def train_all(args, gpus: int) -> dict[Row, dict]:
    """Every run, in table order: per strategy, with ``--side-by-side`` on a machine of several
    GPUs, its first config alone (when it is a one-GPU one) and then every config, the one-GPU
    ones side by side; else every config alone, one after another."""
    runs = [(s, c) for s in args.strategies for c in args.configs]
    if not (args.side_by_side and gpus > 1):
        return {(s, c, "alone"): train(s, c, args) for s, c in runs}
    singles = [run for run in runs if parse_config(run[1])[0] == 1]
    free = list(range(gpus))

    def on_a_free_gpu(run):
        gpu = free.pop()  # list.pop and append are atomic under the GIL; never more runs than GPUs
        try:
            return train(*run, args, gpu=gpu)
        finally:
            free.append(gpu)

    with ThreadPoolExecutor(max_workers=gpus) as pool:
        beside = dict(zip(singles, pool.map(on_a_free_gpu, singles)))
    rows: dict[Row, dict] = {}
    for strategy in args.strategies:
        first = args.configs[0]
        if parse_config(first)[0] == 1:  # the speed-ups' baseline, alone on the machine
            rows[(strategy, first, "alone")] = train(strategy, first, args, alone=True)
        for config in args.configs:
            if (strategy, config) in beside:
                rows[(strategy, config, "side by side")] = beside[(strategy, config)]
            else:
                rows[(strategy, config, "alone")] = train(strategy, config, args)
    return rows


def table(rows: dict[Row, dict], machine: str, args, side_by_side: bool = False) -> str:
    """The markdown table of the runs, with what they ran on; speed-ups against each strategy's
    first row (in side-by-side mode its first config alone)."""
    day = datetime.date.today().isoformat()
    scene = f"{os.path.basename(os.path.normpath(args.data))} `{args.images or 'images'}`"
    twice = {(strategy, config) for strategy, config, ran in rows if ran == "side by side"}  # and alone
    names = {row: f"{row[0]} {row[1]}" + (" alone" if row[:2] in twice and row[2] == "alone" else "") for row in rows}
    shared, sharing = gpu_sharing({names[row]: m for row, m in rows.items() if "skipped" not in m})
    how = (
        f"on {machine}: the one-GPU runs side by side, each on a GPU of its own and sharing the host, except the "
        'baseline of the speed-ups ("alone"), and the others alone on the machine, one after another'
        if side_by_side
        else f"one after another on {machine}"
    )
    run_header, run_rule = ("| run ", "|---") if side_by_side else ("", "")
    # what every run was trained with beyond the defaults: the table is read without its command
    options = "".join(f" --train-option={shlex.quote(option)}" for option in args.train_options)
    lines = [
        f"{scene}, {args.iters:,} views seen per run, {how}{sharing}, {day}, "
        f"commit {commit()} (`python benchmarks/scaling_table.py{options}`):",
        "",
        f"| strategy | GPUs × batch {run_header}| steps | training | images/s | speed-up | PSNR | SSIM | LPIPS-VGG "
        "| LPIPS-Alex | Gaussians | peak GB / GPU | all-reduce | wait |",
        f"|---|---{run_rule}|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    notes: dict[float, bool] = {}  # --run-timeout of the runs stopped after writing their results
    first: dict[str, float] = {}  # the speed-ups' baseline: a strategy's first finished run alone
    shared_baseline = set()  # strategies whose baseline shared its GPU: their speed-ups are marked too
    for (strategy, config, ran), m in rows.items():
        if "skipped" not in m and ran == "alone" and strategy not in first:
            first[strategy] = m["iterations"] / m["train_seconds"]
            if names[(strategy, config, ran)] in shared:
                shared_baseline.add(strategy)
    for (strategy, config, ran), m in rows.items():
        processes, batch = parse_config(config)
        label = f"{processes} × {batch}" + (" †" if names[(strategy, config, ran)] in shared else "")
        stopped = (m.get("neighbours") or {}).get("stopped_after")
        if stopped is not None:
            label += " ‡"
            notes[stopped] = True
        label += f" | {ran}" if side_by_side else ""
        if "skipped" in m:
            lines.append(f"| {strategy} | {label} | skipped: {m['skipped']} |" + " |" * 11)
            continue
        test = m.get("test", {})
        rate = m["iterations"] / m["train_seconds"]
        speedup = f"{rate / first[strategy]:.2f}×" if strategy in first else "—"
        speedup += " †" if strategy in shared_baseline and speedup != "—" else ""
        peaks = [p for p in m.get("peak_gpu_memory_gb_per_process") or [m.get("peak_gpu_memory_gb")] if p is not None]
        comm = m.get("communication") or {}
        share = f"{comm['share'] * 100:.0f}% ({comm['all_reduce_ms_per_step']:.2f} ms)" if "share" in comm else "—"
        wait = f"{comm['wait_share'] * 100:.0f}% ({comm['wait_ms_per_step']:.2f} ms)" if "wait_share" in comm else "—"
        lines.append(
            f"| {strategy} | {label} | {-(-m['iterations'] // batch):,} | {m['train_seconds']:.1f} s | {rate:.1f} "
            f"| {speedup} | {_number(test.get('psnr'), 2)} | {_number(test.get('ssim'), 4)} "
            f"| {_number(test.get('lpips_vgg'), 4)} | {_number(test.get('lpips_alex'), 4)} | {m['num_gaussians']:,} "
            f"| {_number(max(peaks), 2) if peaks else '—'} | {share} | {wait} |"
        )
    for limit in notes:
        lines += ["", f"‡ stopped after {limit:.0f} s: the run had written its results, but its processes did not end."]
    unknown = [f"{strategy} {config}" for (strategy, config, _), m in rows.items() if m.get("options_unknown")]
    if unknown:
        lines += [
            "",
            f"Read from folders trained before runs recorded their options, so not checked against the heading's: "
            f"{', '.join(unknown)}.",
        ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_arguments(parser)
    parser.add_argument("--strategies", nargs="+", default=["3dgs", "cdc"], help="default: 3dgs cdc")
    parser.add_argument(
        "--configs", nargs="+", default=DEFAULT_CONFIGS, help=f"GxB each; default: {' '.join(DEFAULT_CONFIGS)}"
    )
    parser.add_argument("--warmup", type=int, default=20, help="iterations of the untimed launch before each run")
    parser.add_argument("--device", default="auto", help="auto (a GPU per process) or cpu")
    parser.add_argument(
        "--run-timeout",
        type=float,
        default=1800.0,
        help="seconds after which a launch is stopped (0: never); a timed run stopped after writing its results is kept, with a note",
    )
    parser.add_argument(
        "--side-by-side",
        action="store_true",
        help="run the one-GPU configs at the same time, each on a GPU of its own (they share the host)",
    )
    args = parser.parse_args(argv)
    check_common_arguments(parser, args)
    if args.warmup < 0:
        parser.error(f"--warmup must not be negative, got {args.warmup}")
    if args.run_timeout < 0:
        parser.error(f"--run-timeout must not be negative, got {args.run_timeout}")
    if args.device not in ("auto", "cpu"):
        parser.error(f"--device must be auto or cpu, got {args.device!r}")
    if args.side_by_side and args.device == "cpu":
        parser.error("--side-by-side puts each run on a GPU of its own: not with --device cpu")
    if args.docs and not os.path.isfile(args.docs):
        parser.error(f"--docs {args.docs!r} is not a file")
    for config in args.configs:
        try:
            parse_config(config)
        except ValueError as err:
            parser.error(f"--configs: {err}")
    from cdcgs.train.presets import PRESETS

    unknown = [s for s in args.strategies if s not in PRESETS]
    if unknown:
        parser.error(f"--strategies: unknown {', '.join(unknown)} (one of {', '.join(PRESETS)})")
    os.makedirs(args.out, exist_ok=True)
    gpus = available_gpus()
    side_by_side = args.side_by_side and gpus > 1
    if args.side_by_side and not side_by_side:
        print(f"--side-by-side: {gpus} GPU(s) here, so the runs go one after another", flush=True)
    rows = train_all(args, gpus)
    devices = {m["device"] for m in rows.values() if "device" in m}
    machine = " / ".join(sorted(devices)) or "unknown"
    if gpus > 1 and args.device != "cpu":
        machine = f"a machine with {gpus} × {machine}"
    text = table(rows, machine, args, side_by_side)
    print("\n" + text)
    with open(os.path.join(args.out, "scaling.md"), "w") as f:
        f.write(text)
    if args.docs:
        write_docs(args.docs, text, BEGIN, END)
        print(f"written into {args.docs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
