"""Whole trainings one after another on one GPU, and their table written into the docs.

    python benchmarks/training_table.py --data ../shared/data/bonsai --images images --out runs \
        [--runs 3dgs fast cdc gsplat] [--iters 30000] [--docs docs/benchmarks.md]

Each run is its own process, started after the one before it ended, so that none of them shares
the GPU or the host with another; each is preceded by a 20-iteration run of the same command into
a scratch folder, so that compiling kernels (Warp's, gsplat's JIT extension) stays out of the
timed one. What else uses the GPU is not up to this script: during each timed run nvidia-smi
counts the processes computing on its GPU every few seconds (``gpu_neighbours.json`` in the run's
folder), and the table says which runs shared it (their times are not timings) or could not be
checked (no nvidia-smi, or one that lists no process here). The runs:

- ``3dgs``, ``fast``, ``cdc``, any other ``cdcgs train --strategy`` preset: ``cdcgs train`` with
  its defaults (the default runs: ``3dgs fast cdc gsplat``);
- ``3dgs-gsplat-rates``: ``3dgs`` with gsplat's opacity learning rate and initial scales
  (``--lr-opacity-logits 0.05 --scale-rule 3dgs``), the row to set beside gsplat;
- ``gsplat``: gsplat's DefaultStrategy through ``benchmarks/peers/gsplat_train.py`` (the same data,
  loss, initialisation and evaluation); skipped, and said so, where gsplat or CUDA is missing;
- any of these with options of its command after ``@``, each ``NAME=VALUE`` or ``NAME`` (a flag):
  ``cdc@scale-rule=3dgs``, ``3dgs@optimizer=selective@seed=1``, ``gsplat@strategy=mcmc@cap-max=901363``
  (its folder: ``cdc_scale-rule-3dgs``, ...). A run's own ``seed`` replaces ``--seed``.

The table (training time, it/s, test PSNR, SSIM, LPIPS-VGG and -Alex, Gaussians, peak GPU
memory, with the machine, date and commit) is printed, written to ``--out``/table.md and, with
``--docs``, put into that file between the markers ``<!-- training-table:begin -->`` and
``<!-- training-table:end -->`` (they must be there). Runs whose folder already holds a finished
run are read, not trained again (``--retrain`` trains them anew).
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)  # the checkout's cdcgs, which the runs use too

from cdcgs.cli import ask_for_expandable_segments

BEGIN, END = "<!-- training-table:begin -->", "<!-- training-table:end -->"
GSPLAT_RATES = ["--lr-opacity-logits", "0.05", "--scale-rule", "3dgs"]
DEFAULT_RUNS = ["3dgs", "fast", "cdc", "gsplat"]  # issue 21's side by side
USAGE_ERROR = 2  # the exit status of `cdcgs train` (and argparse) for options it refuses
NEIGHBOURS = "gpu_neighbours.json"  # in a run's folder: what the watch saw of the other processes on its GPU


def parse_run(run: str) -> tuple[str, list[str]]:
    """(base run, its own options as command-line arguments) of ``NAME@OPTION=VALUE@FLAG...``."""
    base, *options = run.split("@")
    extra = []
    for option in options:
        name, equals, value = option.partition("=")
        if not name or name.startswith("-") or (equals and not value):
            raise ValueError(f"run {run!r}: {option!r} is not NAME=VALUE or NAME")
        extra += [f"--{name}", value] if equals else [f"--{name}"]
    return base, extra


def folder_name(run: str) -> str:
    """The run's folder under --out: ``cdc@scale-rule=3dgs`` -> ``cdc_scale-rule-3dgs``."""
    return run.replace("@", "_").replace("=", "-")


def command(run: str, args, out: str, iters: int) -> list[str]:
    """The command line of one run."""
    base, own = parse_run(run)  # last on the command line: a run's own --seed wins over --seed
    common = ["--data", args.data, "--out", out, "--iters", str(iters), "--seed", str(args.seed)]
    if args.images:
        common += ["--images", args.images]
    if base == "gsplat":
        peer = os.path.join(HERE, "peers", "gsplat_train.py")
        return [sys.executable, peer, *common, "--no-progress", "--overwrite", *own]
    strategy, extra = (base, []) if base != "3dgs-gsplat-rates" else ("3dgs", GSPLAT_RATES)
    train = [sys.executable, "-m", "cdcgs", "train", *common, "--strategy", strategy, *extra]
    return [*train, "--no-progress", "--checkpoint-every", "0", "--overwrite", *args.train_options, *own]


def gsplat_missing() -> str | None:
    """Why the gsplat peer cannot run here, or None."""
    sys.path.insert(0, os.path.join(HERE, "peers"))
    try:
        import gsplat_train

        _, problems = gsplat_train.load_gsplat()
    finally:
        sys.path.pop(0)
    return "; ".join(problems) if problems else None


WATCH_EVERY = 5.0  # seconds between looks at the GPU during a timed run


CPU_RUN = {"device": "cpu"}  # what the watch records of a run on the CPU: nothing to watch


def on_cpu(train_options: list[str]) -> bool:
    """Whether the extra ``cdcgs train`` options put the runs on the CPU (``--device cpu``)."""
    words = " ".join(train_options).replace("=", " ").split()
    return any(a == "--device" and b == "cpu" for a, b in itertools.pairwise(words))


def visible_gpu() -> str:
    """The GPU a one-GPU run uses, as nvidia-smi names it: the first of CUDA_VISIBLE_DEVICES (an
    index or a UUID), else 0."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",")[0].strip()
    return visible or "0"


def gpu_process_count(gpu: str) -> int | None:
    """How many processes compute on ``gpu`` now (nvidia-smi), or None where it cannot tell."""
    try:
        done = subprocess.run(
            ["nvidia-smi", "--query-compute-apps=pid", "--format=csv,noheader", f"--id={gpu}"],
            capture_output=True,
            text=True,
            timeout=30,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if done.returncode != 0:
        return None
    pids = [int(line) for line in done.stdout.split() if line.strip().isdigit()]
    return sum(1 for pid in pids if pid != os.getpid())  # this table's own process is not a neighbour


def run_watched(
    cmd: list[str], gpus: list[str], every: float = WATCH_EVERY, limit: float | None = None, **kwargs
) -> tuple[int, dict]:
    """Run ``cmd`` (one process on each of ``gpus``, as nvidia-smi names them) to its end, looking
    every ``every`` seconds at how many processes compute on each. Returns (exit status, what was
    seen): ``looks`` (those that saw the run's own process on a GPU: at least one process there)
    and ``most_others`` (the largest count beyond it on any GPU); ``most_others`` is None when no
    look saw the run (nvidia-smi missing, or blind to this container's processes): not checked.
    ``limit``: seconds after which the run is stopped (its whole process group); what was seen
    then says ``stopped_after`` and the status is the stopped process's."""
    looks, most_others = 0, None
    started = time.monotonic()
    # A session of its own, so that a stop reaches every process of the run (torchrun's workers
    # start sessions of their own too: the agent forwards SIGTERM to them).
    with subprocess.Popen(cmd, start_new_session=True, **kwargs) as process:
        try:
            while True:
                try:
                    status = process.wait(timeout=every)
                    break
                except subprocess.TimeoutExpired:
                    pass
                if limit is not None and time.monotonic() - started > limit:
                    stop_group(process)
                    return process.returncode, {
                        "gpus": list(gpus),
                        "looks": looks,
                        "most_others": most_others,
                        "stopped_after": limit,
                    }
                counts = [count for count in map(gpu_process_count, gpus) if count]  # 0: not there (yet)
                if counts:
                    looks += 1
                    most_others = max(most_others or 0, max(counts) - 1)
        except BaseException:  # Ctrl-C, or a failed look: the run does not outlive the table
            stop_group(process)
            raise
    return status, {"gpus": list(gpus), "looks": looks, "most_others": most_others}


def stop_group(process: subprocess.Popen, grace: float = 10.0) -> None:
    """SIGTERM to the process group of ``process`` (a run stops cleanly on it), SIGKILL after
    ``grace`` seconds if it still runs."""
    for sig, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, None)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            return
        try:
            process.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def gpu_sharing(rows: dict[str, dict]) -> tuple[list[str], str]:
    """(the runs that shared a GPU with other processes, words for a table's header about it) of
    trained runs' metrics, each with what the watch saw (``neighbours``) or without (unchecked)."""
    on_gpus = {name: m for name, m in rows.items() if (m.get("neighbours") or {}).get("device") != "cpu"}
    seen = {name: (m.get("neighbours") or {}).get("most_others") for name, m in on_gpus.items()}
    shared = [name for name, others in seen.items() if others]
    unchecked = [name for name, others in seen.items() if others is None]
    words = ""
    if seen and not shared and not unchecked:
        words = f", each alone on its GPU (nvidia-smi looked every {WATCH_EVERY:g} s)"
    if shared:
        words += f"; {', '.join(shared)} shared the GPU with other processes (marked †): their times are not timings"
    if unchecked:
        words += f"; not checked for other processes on the GPU: {', '.join(unchecked)}"
    return shared, words


def train(run: str, args) -> dict:
    """Train one run (a warm-up first) and return its metrics.json, or {"skipped": why}."""
    folder = os.path.join(args.out, folder_name(run))
    metrics_path = os.path.join(folder, "metrics.json")
    if os.path.isfile(metrics_path) and not args.retrain:
        print(f"{run}: read the finished run in {folder}", flush=True)
        return read_run(folder)
    if parse_run(run)[0] == "gsplat":
        why = gsplat_missing()
        if why:
            print(f"gsplat: skipped ({why})", flush=True)
            return {"skipped": why}
    scratch = os.path.join(args.out, f".warm-{folder_name(run)}")
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")]))}
    environment.setdefault("CUDA_DEVICE_ORDER", "PCI_BUS_ID")  # CUDA's indices as nvidia-smi's, for the watch
    ask_for_expandable_segments(environment)  # as `cdcgs train` sets it for itself: gsplat's runs get it too
    for iters, out in ((min(20, args.iters), scratch), (args.iters, folder)):
        print(f"{run}: {' '.join(command(run, args, out, iters)[1:])}", flush=True)
        if out == folder and not on_cpu(args.train_options):  # the timed run: is it alone on its GPU?
            status, seen = run_watched(command(run, args, out, iters), [visible_gpu()], cwd=ROOT, env=environment)
        elif out == folder:
            status, seen = subprocess.run(command(run, args, out, iters), cwd=ROOT, env=environment).returncode, CPU_RUN
        else:
            status = subprocess.run(command(run, args, out, iters), cwd=ROOT, env=environment).returncode
            base, own = parse_run(run)
            if status == USAGE_ERROR and own:  # e.g. --target-gaussians: its densification step is past the warm-up
                print(
                    f"{run}: the {iters}-iteration warm-up refused the run's own options; it warms up {base}",
                    flush=True,
                )
                status = subprocess.run(command(base, args, out, iters), cwd=ROOT, env=environment).returncode
        if status != 0:
            raise SystemExit(f"training_table: {run} failed (exit status {status}); see its output above")
    shutil.rmtree(scratch, ignore_errors=True)
    with open(os.path.join(folder, NEIGHBOURS), "w") as f:
        json.dump(seen, f)
    return read_run(folder)


def read_run(folder: str) -> dict:
    """A finished run's metrics.json, with what the watch saw of its GPU (``neighbours``; absent
    for a run trained before the watch existed)."""
    with open(os.path.join(folder, "metrics.json")) as f:
        metrics = json.load(f)
    path = os.path.join(folder, NEIGHBOURS)
    if os.path.isfile(path):
        with open(path) as f:
            metrics["neighbours"] = json.load(f)
    return metrics


def commit() -> str:
    """HEAD's short hash, and "+ uncommitted changes" when tracked files differ from it (a tree
    that was edited, or copied onto a GPU machine beside an older ``.git``, is not that commit)."""

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()

    try:
        head = git("rev-parse", "--short", "HEAD")
        changed = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"{head} + uncommitted changes" if changed else head


def _number(value, digits: int) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def table(rows: dict[str, dict], machine: str, iters: int, data: str, images: str | None) -> str:
    """The markdown table of the runs, with what they ran on."""
    day = datetime.date.today().isoformat()
    scene = f"{os.path.basename(os.path.normpath(data))} `{images or 'images'}`"
    trained = {run: m for run, m in rows.items() if "skipped" not in m}
    shared, sharing = gpu_sharing(trained)
    how = f"one after another on {machine}{sharing}"
    lines = [
        f"{scene}, {iters:,} iterations, {how}, {day}, commit {commit()} (`python benchmarks/training_table.py`):",
        "",
        "| run | training time | it/s | test PSNR | SSIM | LPIPS-VGG | LPIPS-Alex | Gaussians | peak GPU memory |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for run, m in rows.items():
        if "skipped" in m:
            lines.append(f"| {run} | skipped: {m['skipped']} | | | | | | | |")
            continue
        test = m.get("test", {})
        memory = m.get("peak_gpu_memory_gb")
        lines.append(
            f"| {run}{' †' if run in shared else ''} | {m['train_seconds']:.1f} s | {m['iterations_per_second']:.1f} | {_number(test.get('psnr'), 2)} "
            f"| {_number(test.get('ssim'), 3)} | {_number(test.get('lpips_vgg'), 3)} | {_number(test.get('lpips_alex'), 3)} "
            f"| {m['num_gaussians']:,} | {_number(memory, 2) + ' GB' if memory is not None else '—'} |"
        )
    peer = rows.get("gsplat", {})
    if "train_seconds" in peer:
        for run in rows:
            if run != "gsplat" and "train_seconds" in rows[run]:
                ratio = rows[run]["train_seconds"] / peer["train_seconds"]
                caveat = " (not a timing: one of the two shared its GPU)" if {run, "gsplat"} & set(shared) else ""
                lines.append(f"\n`{run}` took {ratio:.2f}× gsplat's training time{caveat}.")
    return "\n".join(lines) + "\n"


def write_docs(path: str, text: str, begin: str = BEGIN, end: str = END) -> None:
    """Replace what lies between the markers ``begin`` and ``end`` in the file ``path`` by ``text``."""
    with open(path) as f:
        content = f.read()
    if begin not in content or end not in content or content.index(begin) > content.index(end):
        raise SystemExit(f"{path} has no {begin} ... {end} block to write the table into")
    head, rest = content.split(begin, 1)
    _, tail = rest.split(end, 1)
    with open(path, "w") as f:
        f.write(f"{head}{begin}\n{text}{end}{tail}")


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that every table script of benchmarks/ shares."""
    parser.add_argument("--data", required=True, help="scene folder")
    parser.add_argument("--images", default=None, help="image folder of the scene, e.g. images")
    parser.add_argument("--out", required=True, help="folder of the runs (one subfolder each)")
    parser.add_argument("--iters", type=int, default=30_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--docs", default=None, help="markdown file with the table's markers")
    parser.add_argument("--retrain", action="store_true", help="train runs whose folder already holds one")
    parser.add_argument(
        "--train-option", dest="train_options", action="append", default=[], help="extra cdcgs train argument"
    )


def check_common_arguments(parser: argparse.ArgumentParser, args) -> None:
    if not os.path.isdir(args.data):
        parser.error(f"--data {args.data!r} is not a folder")
    if args.iters < 1:
        parser.error(f"--iters must be positive, got {args.iters}")
    if args.docs and not os.path.isfile(args.docs):
        parser.error(f"--docs {args.docs!r} is not a file")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_arguments(parser)
    parser.add_argument("--runs", nargs="+", default=DEFAULT_RUNS, help=f"default: {' '.join(DEFAULT_RUNS)}")
    args = parser.parse_args(argv)
    check_common_arguments(parser, args)
    from cdcgs.train.presets import PRESETS

    unknown = []
    for run in args.runs:
        try:
            base, _ = parse_run(run)
        except ValueError as err:
            parser.error(f"--runs: {err}")
        if base not in (*PRESETS, "3dgs-gsplat-rates", "gsplat"):
            unknown.append(run)
    if unknown:
        parser.error(f"--runs: unknown {', '.join(unknown)} (presets, 3dgs-gsplat-rates or gsplat, each with @options)")
    os.makedirs(args.out, exist_ok=True)
    rows = {run: train(run, args) for run in args.runs}
    machines = {m["device"] for m in rows.values() if "device" in m}
    text = table(rows, " / ".join(sorted(machines)) or "unknown", args.iters, args.data, args.images)
    print("\n" + text)
    with open(os.path.join(args.out, "table.md"), "w") as f:
        f.write(text)
    if args.docs:
        write_docs(args.docs, text)
        print(f"written into {args.docs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
