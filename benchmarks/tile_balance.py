"""How unevenly a render's work falls on its tiles: what the blend adjoint's tail costs.

    python benchmarks/tile_balance.py --data SCENE [--images images] [--ply MODEL]
        [--gaussians 1000000] [--views 0 1 2] [--slots 528] [--overhead 50] [--chunks 256 512 1024]
        [--out balance.json]

The blend kernels give each 16 x 16 tile one block. The adjoint's block walks its tile's list
from the last contributor of any of its pixels down to the list's start, so its time grows with
that walk; the GPU starts a launch's blocks about in their order, and a long walk started late
runs alone at the end. For each view this renders the model (the scene's points resampled to
``--gaussians`` as ``profile_step.py`` does, or a trained ``--ply`` as it is), measures each
tile's list length and backward walk, and schedules the walks greedily onto ``--slots``
concurrent blocks (132 SMs x 4 blocks of 256 threads on an H100), each walk costing its length plus
``--overhead``: in tile-number order (as the kernels take them), longest list first (a reordering),
the bounds of any order (the longest walk) and of walks split evenly (the total over the slots),
and the chunked adjoint's blocks for each of ``--chunks``. Printed per view: the walks (largest, mean) and each makespan over the numbered one. A
model of the scheduling, not a timing: a block alone on an SM runs faster than one sharing it,
which this ignores.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import sys
import tempfile

import torch

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from profile_step import prepared

from cdcgs.io import read_ply
from cdcgs.train.model import GaussianModel


def tile_walks(info) -> tuple[torch.Tensor, torch.Tensor]:
    """(list length, backward walk) of each tile of a render: the walk is the block's, from the
    largest last contributor of its pixels down to the list's start (0 for an empty list)."""
    ranges = info.tile_ranges.cpu().long()
    lengths = ranges[:, 1] - ranges[:, 0]
    last = info.last_contributor.cpu().long()
    height, width = last.shape
    tiles_y, tiles_x, size = info.tiles_y, info.tiles_x, info.tile_size
    padded = torch.full((tiles_y * size, tiles_x * size), -1, dtype=torch.long)
    padded[:height, :width] = last
    block_last = padded.view(tiles_y, size, tiles_x, size).amax(dim=(1, 3)).reshape(-1)
    walks = torch.where(lengths > 0, (block_last - ranges[:, 0] + 1).clamp(min=0), torch.zeros_like(lengths))
    return lengths, walks


def makespan(costs: list[float], slots: int, order: list[int]) -> float:
    """When the last of the jobs ends, each of ``order`` taken in turn by the slot free first."""
    ends = [0.0] * slots
    for job in order:
        heapq.heappush(ends, heapq.heappop(ends) + costs[job])
    return max(ends)


def chunked_costs(walks: list[int], chunk: int, overhead: float) -> list[float]:
    """The blocks of the chunked adjoint (``cdcgs.render.BLEND_CHUNK``): each tile's walk cut into
    pieces of at most ``chunk`` entries (a tile that walks nothing keeps no block), each costing
    its piece plus ``overhead``."""
    costs = []
    for walk in walks:
        for first in range(0, walk, chunk):
            costs.append(min(chunk, walk - first) + overhead)
    return costs


def balance(
    lengths: torch.Tensor, walks: torch.Tensor, slots: int, overhead: float, chunks: tuple[int, ...] = ()
) -> dict:
    costs = [float(w) + overhead for w in walks.tolist()]
    numbered = makespan(costs, slots, list(range(len(costs))))
    longest = sorted(range(len(costs)), key=lambda t: (-int(lengths[t]), t))  # as the binning orders them
    return {
        "tiles": len(costs),
        "walk_max": int(walks.max()),
        "walk_mean": float(walks.float().mean()),
        "numbered": numbered,
        "longest_first": makespan(costs, slots, longest),
        "any_order": max(sum(costs) / slots, max(costs)),  # no order ends before the longest walk
        "split": sum(costs) / slots,  # walks cut into pieces that fill every slot evenly
        "chunked": {
            str(chunk): makespan(pieces, slots, list(range(len(pieces))))
            for chunk in chunks
            for pieces in [chunked_costs(walks.tolist(), chunk, overhead)]
        },
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="scene folder")
    parser.add_argument("--images", default=None, help="image folder of the scene, e.g. images")
    parser.add_argument("--ply", default=None, help="a trained model (else the scene's points, resampled)")
    parser.add_argument("--gaussians", type=int, default=1_000_000, help="without --ply: the resampled count")
    parser.add_argument("--views", type=int, nargs="+", default=[0], help="training views to render")
    parser.add_argument("--slots", type=int, default=528, help="blocks the GPU runs at once")
    parser.add_argument("--overhead", type=float, default=50.0, help="a block's cost besides its walk")
    parser.add_argument(
        "--chunks", type=int, nargs="*", default=[256, 512, 1024], help="chunk sizes of the chunked adjoint to model"
    )
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    if not os.path.isdir(args.data):
        parser.error(f"--data {args.data!r} is not a folder")
    if args.ply and not os.path.isfile(args.ply):
        parser.error(f"--ply {args.ply!r} is not a file")
    if args.slots < 1 or args.overhead < 0 or any(c < 1 for c in args.chunks):
        parser.error("--slots and --chunks must be at least 1 and --overhead at least 0")
    setup = argparse.Namespace(
        data=args.data,
        images=args.images,
        ply=args.ply,
        strategy="3dgs",
        reference_loss=False,
        torch_adam=False,
        at=20_000,
    )
    count = args.gaussians
    if args.ply:  # the model as it is (prepared() resamples to the count: here all of them)
        count = GaussianModel.from_ply(read_ply(args.ply)).num
    with tempfile.TemporaryDirectory() as out:
        trainer = prepared(setup, count, out)
    views = len(trainer.scene.train)
    if any(not 0 <= v < views for v in args.views):
        parser.error(f"--views: the scene has {views} training views (0 to {views - 1})")
    rows = []
    for view in args.views:
        with torch.no_grad():
            _, _, info = trainer._render(view)
        row = {
            "view": view,
            "gaussians": trainer.model.num,
            **balance(*tile_walks(info), args.slots, args.overhead, tuple(args.chunks)),
        }
        rows.append(row)
        print(
            f"view {view}: {row['tiles']} tiles, walk max {row['walk_max']} mean {row['walk_mean']:.0f}; "
            f"makespan numbered {row['numbered']:.0f}; over it: longest first "
            f"{row['longest_first'] / row['numbered']:.3f}, the best order {row['any_order'] / row['numbered']:.3f}, "
            f"walks split evenly {row['split'] / row['numbered']:.3f}"
            + "".join(f", chunks of {c} {m / row['numbered']:.3f}" for c, m in row["chunked"].items()),
            flush=True,
        )
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"args": vars(args), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
