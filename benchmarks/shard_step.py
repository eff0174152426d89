"""The render of a step on sharded Gaussians against data parallelism's, on several processes.

    torchrun --standalone --nproc_per_node=2 benchmarks/shard_step.py --data SCENE --images images \
        [--ply run/point_cloud.ply] [--gaussians 1000000 6000000] [--repeats 20] [--out shard_step.json] [--device auto]

For each count N, every process holds the same N Gaussians (those of ``--ply``, a trained model,
or the scene's points, resampled to N as ``benchmarks/profile_step.py`` does, SH degree 3), and
process r renders training view (step x W + r) of the scene at each timed step. Four ways, each
timed per step with a synchronisation before and after (the median of ``--repeats`` steps after two
untimed ones):

- ``one view``: the whole scene rendered into the process's view, forward and backward of a
  weighted sum of the image (what one process does per view);
- ``data parallel``: the same, then ``Ranks.reduce_gradients`` of the six parameters' gradients
  (59 floats a Gaussian; the densification statistics that a training sends with them are left
  out);
- ``sharded``: :func:`cdcgs.train.shards.rasterize_shard` with the process's slice of the N
  Gaussians (N / W each, in order), forward and backward;
- ``sharded, visible only``: the same with ``visible_only`` (each view sent only what it sees).

On CUDA the first three are also timed as training replays its steps: captured once as a CUDA
graph (each process's views chosen on the device before each replay, the pairs binned into slots,
``capacity``, sized from every view's count with a margin, nothing read on the host) and replayed:
``one view, replayed``, ``data parallel, replayed`` (the all-reduce in the graph) and ``sharded,
replayed`` (the transfers in the graph); their speed-ups are over the sum of the processes' replayed
one-view medians, in a second table.

What W processes would gain over one for the render and its exchange alone is the time one
process takes for the step's W views (the sum of the processes' ``one view`` medians) over the
step: printed as each way's "speed-up" (Adam, the loss and the host's other work per step are not
in it; sharded, each process's Adam would update N / W Gaussians instead of N). A barrier before
each timed round starts the processes together. Rank 0
prints the table and writes ``--out`` (JSON) with the machine and the date. ``--device auto``
puts process i on GPU i (NCCL), ``cpu`` runs on the CPU (gloo).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import sys

import torch
import torch.distributed as dist
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))

from allreduce import join, launch_options, publish, report_of, timed
from profile_step import resampled

from cdcgs._interop import launch, warp_scope, wp_arg
from cdcgs.io import load_scene, read_ply
from cdcgs.kernels import Camera
from cdcgs.kernels._lookahead import select_camera_at_kernel
from cdcgs.render import prepare_camera, rasterize
from cdcgs.train.distributed import Ranks
from cdcgs.train.model import GaussianModel
from cdcgs.train.shards import rasterize_shard

WAYS = ("one_view", "data_parallel", "sharded", "sharded_visible")
REPLAYED = ("one_view_replayed", "data_parallel_replayed", "sharded_replayed")
MARGIN = 1.25  # the slots of a replayed render: the most pairs of any view, times this


class Replay:
    """Steps captured as CUDA graphs: the step's W views chosen on the device from ``where``
    (written before each replay), as a training's replayed step chooses its view."""

    def __init__(self, device: torch.device, cameras: list, world: int):
        self.device = device
        self.table = wp.array([c.camera for c in cameras], dtype=Camera, device=wp.device_from_torch(device))
        self.slots = [wp.empty(1, dtype=Camera, device=self.table.device) for _ in range(world)]
        self.views = [dataclasses.replace(cameras[0], on_device=slot) for slot in self.slots]
        self.where = torch.zeros(world, dtype=torch.int32, device=device)
        # the stream of the warm-up and the capture, where the replayed steps' leaves are made too
        # (autograd accumulates a leaf's gradient in step with the stream it was made on)
        self.stream = torch.cuda.Stream(device)

    def capture(self, body, reset) -> torch.cuda.CUDAGraph:
        """``body`` run twice on a side stream (as torch asks of a warm-up before a capture), then
        captured; ``reset()`` before each (the gradients set to None)."""
        side = self.stream
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(2):
                reset()
                self._select()
                body()
        torch.cuda.synchronize(self.device)
        reset()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, stream=side, capture_error_mode="thread_local"):
            stream = wp.stream_from_torch(torch.cuda.current_stream(self.device))
            wp.capture_begin(stream=stream, external=True)
            try:
                self._select()
                body()
            finally:
                wp.capture_end(stream=stream)
        return graph

    def _select(self) -> None:
        with warp_scope(self.device):
            for entry, slot in enumerate(self.slots):
                launch(
                    select_camera_at_kernel, 1, inputs=[self.table, wp_arg(self.where, wp.int32), entry], outputs=[slot]
                )

    def replay(self, graph, views: list[int]) -> None:
        self.where.copy_(torch.tensor(views, dtype=torch.int32))
        graph.replay()


def slices(n: int, world: int) -> list[int]:
    """N Gaussians over ``world`` processes, in order: the first N mod W take one more."""
    return [n // world + (1 if r < n % world else 0) for r in range(world)]


def measure(ranks: Ranks, device: torch.device, source: GaussianModel, cameras: list, n: int, repeats: int) -> dict:
    """The four timings at ``n`` Gaussians (every process calls this with the same ``n``)."""
    generator = torch.Generator(device=device).manual_seed(0)  # the same Gaussians on every process
    model = resampled(source, n, generator)
    params = {k: v.requires_grad_(True) for k, v in model.params.items()}
    world, rank = ranks.world, ranks.rank
    rows = slices(n, world)
    start = sum(rows[:rank])
    mine = {k: v.detach()[start : start + rows[rank]].clone().requires_grad_(True) for k, v in params.items()}
    weight = torch.rand(cameras[0].height, cameras[0].width, 3, device=device, generator=generator)

    def view_of(step: int) -> int:
        return (step * world + rank) % len(cameras)

    def whole(step: int) -> None:
        for p in params.values():
            p.grad = None
        image, _, _ = rasterize(**model.render_args(), camera=cameras[view_of(step)])
        (image * weight).sum().backward()

    def data_parallel(step: int) -> None:
        whole(step)
        ranks.reduce_gradients(params.values(), world)

    def sharded(step: int, visible_only: bool = False) -> None:
        for p in mine.values():
            p.grad = None
        views = [cameras[(step * world + r) % len(cameras)] for r in range(world)]
        image, _, _ = render_slice(mine, model.sh_degree, views, rows, visible_only=visible_only)
        (image * weight).sum().backward()

    row = {"gaussians": n, "slices": rows}
    ways = (whole, data_parallel, sharded, lambda step: sharded(step, visible_only=True))
    for name, call in zip(WAYS, ways):
        steps = itertools.count()  # each round renders the next views
        row[f"{name}_ms"] = timed(
            device, lambda call=call, steps=steps: call(next(steps)), repeats, before=dist.barrier
        )
    # one process rendering the step's W views: the sum of the processes' own views' medians
    row["views_alone_ms"] = sum_over(ranks, device, row["one_view_ms"])
    for name in WAYS[1:]:
        row[f"{name}_speedup"] = row["views_alone_ms"] / row[f"{name}_ms"]
    if device.type == "cuda":
        row.update(measure_replayed(ranks, device, model, mine, rows, cameras, weight, repeats))
    return row


def render_slice(mine: dict, sh_degree: int, views: list, rows: list[int], **options):
    """:func:`rasterize_shard` of this process's slice (a model's parameters, ``mine``)."""
    return rasterize_shard(
        mine["means"],
        mine["quats"],
        mine["log_scales"].exp(),
        torch.sigmoid(mine["opacity_logits"]),
        mine["sh_dc"],
        sh_rest=mine["sh_rest"],
        sh_degree=sh_degree,
        cameras=views,
        rows=rows,
        **options,
    )


def sum_over(ranks: Ranks, device: torch.device, value: float) -> float:
    total = torch.tensor([value], dtype=torch.float64, device=device)
    return float(ranks.all_reduce_(total)[0])


def measure_replayed(ranks, device, model, mine, rows, cameras, weight, repeats) -> dict:
    """The replayed ways (CUDA): each captured once, then timed as the eager ones."""
    world, rank = ranks.world, ranks.rank
    with torch.no_grad():  # the slots: every view's pairs, read once here
        most = max(rasterize(**model.render_args(), camera=c)[2].num_intersections for c in cameras)
    capacity = int(most * MARGIN) + 1
    replay = Replay(device, cameras, world)
    with torch.cuda.stream(replay.stream):  # the leaves of the replayed steps, made on its stream
        torch.cuda.current_stream(device).wait_stream(torch.cuda.default_stream(device))
        model.params.update({k: v.detach().clone().requires_grad_(True) for k, v in model.params.items()})
        mine = {k: v.detach().clone().requires_grad_(True) for k, v in mine.items()}
    params = model.params
    infos = {}

    def whole(name: str, reduce: bool):
        def body():
            image, _, infos[name] = rasterize(**model.render_args(), camera=replay.views[rank], capacity=capacity)
            (image * weight).sum().backward()
            if reduce:
                ranks.reduce_gradients(params.values(), world)

        return body

    def sharded():
        image, _, infos["sharded"] = render_slice(mine, model.sh_degree, replay.views, rows, capacity=capacity)
        (image * weight).sum().backward()

    row = {"capacity": capacity}
    bodies = (whole("one_view", False), whole("data_parallel", True), sharded)

    def reset():
        for p in (*params.values(), *mine.values()):
            p.grad = None

    for name, body in zip(REPLAYED, bodies):
        graph = replay.capture(body, reset)
        steps = itertools.count()

        def step(graph=graph, steps=steps):
            first = next(steps) * world
            replay.replay(graph, [(first + r) % len(cameras) for r in range(world)])

        row[f"{name}_ms"] = timed(device, step, repeats, before=dist.barrier)
        for info in infos.values():
            info.check()  # the last replay's pairs fitted its slots, and nothing was NaN
        infos.clear()
        del graph
    row["views_alone_replayed_ms"] = sum_over(ranks, device, row["one_view_replayed_ms"])
    for name in REPLAYED[1:]:
        row[f"{name}_speedup"] = row["views_alone_replayed_ms"] / row[f"{name}_ms"]
    return row


def table(report: dict) -> str:
    lines = [
        f"{report['processes']} processes ({report['backend']}) on {report['device']}, {report['date']}, "
        f"{report['views']} views of {report['size']}; median of {report['repeats']} steps "
        "(`python benchmarks/shard_step.py`):",
        "",
        "| Gaussians | one view | data parallel | speed-up | sharded | speed-up | sharded, visible only | speed-up |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["rows"]:
        lines.append(
            f"| {r['gaussians']:,} | {r['one_view_ms']:.2f} ms | {r['data_parallel_ms']:.2f} ms "
            f"| {r['data_parallel_speedup']:.2f}× | {r['sharded_ms']:.2f} ms | {r['sharded_speedup']:.2f}× "
            f"| {r['sharded_visible_ms']:.2f} ms | {r['sharded_visible_speedup']:.2f}× |"
        )
    if all("one_view_replayed_ms" in r for r in report["rows"]):
        lines += [
            "",
            f"Replayed as CUDA graphs (slots: the most pairs of any view × {MARGIN}):",
            "",
            "| Gaussians | one view | data parallel | speed-up | sharded | speed-up |",
            "|---:|---:|---:|---:|---:|---:|",
        ]
        for r in report["rows"]:
            lines.append(
                f"| {r['gaussians']:,} | {r['one_view_replayed_ms']:.2f} ms | {r['data_parallel_replayed_ms']:.2f} ms "
                f"| {r['data_parallel_replayed_speedup']:.2f}× | {r['sharded_replayed_ms']:.2f} ms "
                f"| {r['sharded_replayed_speedup']:.2f}× |"
            )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="scene folder (its training views' cameras)")
    parser.add_argument("--images", default=None, help="image folder of the scene, e.g. images")
    parser.add_argument("--ply", default=None, help="a trained model (default: the scene's points)")
    launch_options(parser, [1_000_000, 6_000_000], 20)
    args = parser.parse_args(argv)
    if args.ply is not None and not os.path.isfile(args.ply):
        parser.error(f"--ply {args.ply!r} is not a file")
    ranks, device = join(parser, args)
    try:
        scene = load_scene(args.data, images=args.images, load_images_now=False, progress=False)
        cameras = [prepare_camera(v.viewmat, v.K, v.width, v.height) for v in scene.train]
        if len({(c.width, c.height) for c in cameras}) != 1:
            parser.error(f"--data {args.data!r}: its training views have several sizes; the sharded render takes one")
        if args.ply:
            source = GaussianModel.from_ply(read_ply(args.ply), device=device)
        else:
            source = GaussianModel.from_points(scene.points, scene.colors, device=device)
        source.sh_degree = source.max_sh_degree
        rows = [measure(ranks, device, source, cameras, n, args.repeats) for n in args.gaussians]
    finally:
        ranks.close(wait=True)
    if ranks.is_main:
        size = f"{cameras[0].width} x {cameras[0].height}"
        report = report_of(ranks, device, args, rows, views=len(cameras), size=size)
        publish(report, table(report), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
