"""Where trainings' time went: each run's training time over spans of iterations, from history.json.

    python benchmarks/time_split.py RUN [RUN ...] [--at 500 3000 15000] [--out split.json]

A run folder's history.json records the training time at each log point (``train_seconds``: the
step and the seconds so far, as metrics.json's ``train_seconds`` counts them). For each run this
prints the seconds each span took, with the milliseconds per iteration over it and the Gaussians
at its end, and the run's whole time with its refinements (``refine_seconds``), CDC-GS's Γ passes
(``gamma_seconds``), the CUDA-graph captures (``cuda_graph.capture_seconds``) and the waits before
them for the work queued (``cuda_graph.capture_wait_seconds``) from
metrics.json. The spans end at each of ``--at`` that the run logged, and at its last step.
"""

from __future__ import annotations

import argparse
import json
import os
import sys


def read_run(folder: str) -> tuple[dict, dict]:
    """(history, metrics) of a run folder; ValueError naming the folder when history.json lacks the times."""
    paths = [os.path.join(folder, name) for name in ("history.json", "metrics.json")]
    for path in paths:
        if not os.path.isfile(path):
            raise ValueError(f"{folder!r} has no {os.path.basename(path)}: not a finished cdcgs run folder")
    with open(paths[0]) as f:
        history = json.load(f)
    with open(paths[1]) as f:
        metrics = json.load(f)
    if not history.get("train_seconds"):
        raise ValueError(f"{folder!r}: its history.json has no train_seconds (runs before 73c9c17 did not record them)")
    return history, metrics


def split(history: dict, ends: list[int]) -> list[dict]:
    """The spans from step 0 to each of ``ends`` that the run logged, then to its last logged step:
    each with its first and last step, seconds, ms per iteration and the Gaussians at its end."""
    times = {entry["step"]: entry["seconds"] for entry in history["train_seconds"]}
    gaussians = dict(zip(history["step"], history["gaussians"]))
    last = max(times)
    marks = [step for step in sorted(set(ends)) if step in times and step < last] + [last]
    spans, step, seconds = [], 0, 0.0
    for mark in marks:
        took = times[mark] - seconds
        spans.append(
            {
                "from": step,
                "to": mark,
                "seconds": took,
                "ms_per_iteration": took * 1e3 / (mark - step),
                "gaussians": gaussians.get(mark),
            }
        )
        step, seconds = mark, times[mark]
    return spans


def summary(metrics: dict) -> dict:
    """The run's whole training time and the parts of it that metrics.json names (None: not recorded)."""
    graph = metrics.get("cuda_graph") or {}
    return {
        "train_seconds": metrics["train_seconds"],
        "refine_seconds": metrics.get("refine_seconds"),
        "gamma_seconds": metrics.get("gamma_seconds"),
        "capture_seconds": graph.get("capture_seconds"),
        "capture_wait_seconds": graph.get("capture_wait_seconds"),
    }


def _seconds(value) -> str:
    return "—" if value is None else f"{value:.1f} s"


def print_table(runs: list[dict]) -> None:
    names = [run["name"] for run in runs]
    print("| iterations | " + " | ".join(names) + " |")
    print("|---" * (len(runs) + 1) + "|")
    rows = max(len(run["spans"]) for run in runs)
    for i in range(rows):
        cells, label = [], None
        for run in runs:
            if i < len(run["spans"]):
                span = run["spans"][i]
                label = label or f"{span['from']:,}–{span['to']:,}"
                count = "" if span["gaussians"] is None else f", {span['gaussians'] / 1e6:.2f}M"
                cells.append(f"{span['seconds']:.1f} s ({span['ms_per_iteration']:.2f} ms{count})")
            else:
                cells.append("")
        print(f"| {label} | " + " | ".join(cells) + " |")
    print("| whole run | " + " | ".join(_seconds(run["summary"]["train_seconds"]) for run in runs) + " |")
    for key, label in (
        ("refine_seconds", "refinements"),
        ("gamma_seconds", "Γ passes"),
        ("capture_seconds", "captures"),
        ("capture_wait_seconds", "waits before captures"),
    ):
        print(f"| {label} | " + " | ".join(_seconds(run["summary"][key]) for run in runs) + " |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="run folders (cdcgs train --out)")
    parser.add_argument("--at", type=int, nargs="+", default=[500, 3000, 15000], help="iterations where spans end")
    parser.add_argument("--out", help="also write the spans as JSON here")
    args = parser.parse_args(argv)
    runs = []
    for folder in args.runs:
        try:
            history, metrics = read_run(folder)
        except ValueError as error:
            parser.error(str(error))
        name = os.path.basename(os.path.normpath(folder))
        runs.append({"name": name, "folder": folder, "spans": split(history, args.at), "summary": summary(metrics)})
    print_table(runs)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(runs, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
