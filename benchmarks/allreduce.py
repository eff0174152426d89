"""The gradient exchange of a data-parallel step alone, at the sizes of real runs.

    torchrun --standalone --nproc_per_node=2 benchmarks/allreduce.py \
        [--gaussians 1000000 3000000 6000000] [--repeats 20] [--out allreduce.json] [--device auto]

For each count N, every process holds the gradients of N Gaussians (59 floats each, in the six
tensors of ``cdcgs.train.model.PARAM_NAMES``) and the densification statistics' additions that
`3dgs` sends with them (2 N floats), and times, with a synchronisation before and after each, the
median of ``--repeats`` rounds after two untimed ones:

- ``pack``: the flat buffer alone (``torch.cat``, as ``Ranks.reduce_gradients`` builds it);
- ``all_reduce``: ``all_reduce`` of a buffer of that size alone;
- ``exchange``: ``Ranks.reduce_gradients`` whole (pack, all-reduce, gradients back), as a training
  with FusedAdam calls it: without the division by the batch, which Adam's rates take (before
  63126e0 it was timed with the division);
- ``shards forward`` and ``shards back``: the exchanges of ``--dist-mode shards``' render alone
  (:func:`cdcgs.train.shards._swap`, the point-to-point transfers of one group), with the N
  Gaussians split evenly over the processes: forward, each process sends every other process the 12
  numbers a Gaussian of its slice that the other's view needs (``cdcgs.train.shards.FIELDS``) and
  receives theirs; back, the 10 gradients a Gaussian the reverse way. Each round starts with a
  one-number all-reduce (the processes start together), and what arrives is checked.

Bytes per second are the buffer's bytes over the time (for two processes the same as NCCL's bus
bandwidth); for the shards' exchanges, the bytes one process sends over the time (it receives as
many). NCCL's channels for point-to-point transfers are its environment's
(``NCCL_NCHANNELS_PER_PEER``, ``NCCL_MIN_P2P_NCHANNELS``): the report records every ``NCCL_``
variable of the launch and NCCL's version, so settings are compared by running once per setting. Rank 0 prints the
table and writes ``--out`` (JSON) with the machine and the date.
``--device auto`` puts process i on GPU i (NCCL), ``cpu`` runs on the CPU (gloo).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from cdcgs.train.distributed import Ranks, rank_device
from cdcgs.train.model import PARAM_NAMES
from cdcgs.train.shard_training import even_rows
from cdcgs.train.shards import DIFFERENTIABLE, FIELDS, _swap

# floats per Gaussian of each parameter, in PARAM_NAMES's order (SH of degree 3: 1 + 15 coefficients)
WIDTHS = {"means": 3, "log_scales": 3, "quats": 4, "opacity_logits": 1, "sh_dc": 3, "sh_rest": 45}
STATISTICS = 2  # floats per Gaussian of 3dgs's additions (gradient norms and view counts)


def timed(device: torch.device, call, repeats: int, before=None) -> float:
    """Median milliseconds of ``call()`` over ``repeats`` rounds (two untimed first); ``before()``
    runs before each round's clock starts (e.g. a barrier, so that the processes start together)."""
    times = []
    for round_ in range(repeats + 2):
        if before is not None:
            before()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        call()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        if round_ >= 2:
            times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def measure(ranks: Ranks, device: torch.device, n: int, repeats: int) -> dict:
    """The three timings of one count ``n`` (every process calls this with the same ``n``)."""
    generator = torch.Generator(device=device).manual_seed(ranks.rank)
    params = []
    for name in PARAM_NAMES:
        p = torch.zeros(n, WIDTHS[name], device=device, requires_grad=True)
        p.grad = torch.randn(n, WIDTHS[name], device=device, generator=generator)
        params.append(p)
    extras = [torch.rand(n, device=device, generator=generator) for _ in range(STATISTICS)]
    grads = [p.grad for p in params]
    size = sum(p.numel() for p in params) + sum(e.numel() for e in extras)
    pieces = [g.reshape(-1) for g in grads] + extras
    flat = torch.cat(pieces)  # real values: uninitialised memory may hold denormals, slow on a CPU

    def exchange():
        for p, g in zip(params, grads):  # the step's gradients again (the exchange makes them views of its buffer)
            p.grad = g.clone()
        ranks.reduce_gradients(params, ranks.world, extras, divide=False)

    row = {"gaussians": n, "bytes": 4 * size}
    row["pack_ms"] = timed(device, lambda: torch.cat(pieces), repeats)
    row["all_reduce_ms"] = timed(device, lambda: ranks.all_reduce_(flat), repeats)
    # less the clones that restore the gradients, timed apart
    clones = timed(device, lambda: [g.clone() for g in grads], repeats)
    row["exchange_ms"] = max(timed(device, exchange, repeats) - clones, 0.0)
    for part in ("all_reduce", "exchange"):
        row[f"{part}_gb_per_second"] = row["bytes"] / row[f"{part}_ms"] / 1e6 if row[f"{part}_ms"] > 0 else None
    row.update(shard_exchanges(ranks, device, n, repeats))
    return row


def shard_exchanges(ranks: Ranks, device: torch.device, n: int, repeats: int) -> dict:
    """The sharded render's two exchanges of ``n`` Gaussians in even slices: their times and the
    bytes this process sends in each (it receives as many from the others' slices). A one-number
    all-reduce starts each round, so that the processes start it together. What arrives is checked:
    every value sent from process s to process r is 1 + s + 10 r."""
    rows, rank = even_rows(n, ranks.world), ranks.rank

    def fields(count: int, names, value: float) -> list[torch.Tensor]:
        dtype = {"radii": torch.int32}
        return [
            torch.full((count, width), value, dtype=dtype.get(name, torch.float32), device=device).squeeze(-1)
            for name, width in names
        ]

    gradients = FIELDS[:DIFFERENTIABLE]
    forward = (
        [fields(rows[rank], FIELDS, 1 + rank + 10 * to) for to in range(ranks.world)],
        [fields(count, FIELDS, -1) for count in rows],
    )
    back = (
        [fields(count, gradients, 1 + rank + 10 * to) for to, count in enumerate(rows)],
        [fields(rows[rank], gradients, -1) for _ in rows],
    )
    sent = {
        "forward": (ranks.world - 1) * rows[rank] * sum(4 * width for _, width in FIELDS),
        "back": (n - rows[rank]) * sum(4 * width for _, width in gradients),
    }
    start_together = lambda: ranks.all_reduce_(torch.zeros(1, device=device))
    result = {}
    for part, (outgoing, incoming) in (("forward", forward), ("back", back)):
        exchange = lambda o=outgoing, i=incoming: _swap(o, i, None)  # in the default process group
        result[f"shards_{part}_ms"] = timed(device, exchange, repeats, before=start_together)
        for source, tensors in enumerate(incoming):
            expected = 1 + source + 10 * rank
            if any(t.numel() and not bool((t == expected).all()) for t in tensors):
                raise RuntimeError(f"the shards' {part} exchange delivered wrong values from process {source}")
        result[f"shards_{part}_bytes"] = sent[part]
        ms = result[f"shards_{part}_ms"]
        result[f"shards_{part}_gb_per_second"] = sent[part] / ms / 1e6 if ms > 0 else None
    return result


def table(report: dict) -> str:
    lines = [
        f"{report['processes']} processes ({report['backend']}) on {report['device']}, {report['date']}; "
        f"median of {report['repeats']} rounds (`python benchmarks/allreduce.py`):",
        "",
        "| Gaussians | buffer | pack | all-reduce | GB/s | exchange (whole) | GB/s | shards forward | GB/s "
        "| shards back | GB/s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    keys = ("all_reduce", "exchange", "shards_forward", "shards_back")
    for r in report["rows"]:
        rates = [f"{r[f'{k}_gb_per_second']:.1f}" if r[f"{k}_gb_per_second"] is not None else "—" for k in keys]
        lines.append(
            f"| {r['gaussians']:,} | {r['bytes'] / 1e6:.1f} MB | {r['pack_ms']:.3f} ms | {r['all_reduce_ms']:.3f} ms "
            f"| {rates[0]} | {r['exchange_ms']:.3f} ms | {rates[1]} | {r['shards_forward_ms']:.3f} ms | {rates[2]} "
            f"| {r['shards_back_ms']:.3f} ms | {rates[3]} |"
        )
    nccl = report.get("nccl_env") or {}
    if nccl or report.get("nccl_version"):
        settings = ", ".join(f"{k}={v}" for k, v in sorted(nccl.items())) or "no NCCL_ variables"
        lines += ["", f"NCCL {report.get('nccl_version') or '(not used)'}: {settings}"]
    return "\n".join(lines) + "\n"


def launch_options(parser: argparse.ArgumentParser, gaussians: list[int], repeats: int) -> None:
    """The options of a benchmark run by torchrun on several processes (this one's and shard_step.py's)."""
    parser.add_argument("--gaussians", type=int, nargs="+", default=gaussians)
    parser.add_argument("--repeats", type=int, default=repeats, help="timed rounds (steps)")
    parser.add_argument("--device", default="auto", help="auto (a GPU per process) or cpu")
    parser.add_argument("--out", default=None, help="JSON file of the results (rank 0 writes it)")


def join(parser: argparse.ArgumentParser, args) -> tuple[Ranks, torch.device]:
    """Check :func:`launch_options`' values and join the launch: this process's ranks and device;
    a parser error on one process."""
    if any(n < 1 for n in args.gaussians):
        parser.error(f"--gaussians must be positive, got {args.gaussians}")
    if args.repeats < 1:
        parser.error(f"--repeats must be positive, got {args.repeats}")
    if args.device not in ("auto", "cpu"):
        parser.error(f"--device must be auto or cpu, got {args.device!r}")
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")))
    device = torch.device(rank_device(args.device, local_rank, local_world))
    ranks = Ranks.from_environment(device)
    if not ranks.distributed:
        parser.error("one process: launch with torchrun --nproc_per_node=2 (or more)")
    return ranks, device


def report_of(ranks: Ranks, device: torch.device, args, rows: list[dict], **extra) -> dict:
    """The results with the launch, the machine and the date."""
    return {
        "processes": ranks.world,
        "backend": ranks.backend,
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "date": datetime.date.today().isoformat(),
        "repeats": args.repeats,
        **extra,
        "rows": rows,
    }


def publish(report: dict, text: str, out: str | None) -> None:
    """Rank 0's: print the table, write the JSON."""
    print(text)
    if out:
        with open(out, "w") as f:
            json.dump(report, f, indent=1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    launch_options(parser, [1_000_000, 3_000_000, 6_000_000], 20)
    args = parser.parse_args(argv)
    ranks, device = join(parser, args)
    try:
        rows = [measure(ranks, device, n, args.repeats) for n in args.gaussians]
    finally:
        ranks.close(wait=True)
    if ranks.is_main:
        nccl = {k: v for k, v in os.environ.items() if k.startswith("NCCL_")}
        library = ".".join(map(str, torch.cuda.nccl.version())) if device.type == "cuda" else None
        report = report_of(ranks, device, args, rows, nccl_env=nccl, nccl_version=library)
        publish(report, table(report), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
