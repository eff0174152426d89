"""How much of a scene one training view sees, and how much B random views see together.

    python benchmarks/visible_share.py --data SCENE [--images images] [--ply MODEL] [--batch 2 4]
        [--margin 0.15] [--samples 2000] [--seed 0] [--out share.json]

A data-parallel step all-reduces the gradients of every Gaussian, though only those that the
step's views see have any: exchanging the union of the views' visible Gaussians would carry this
share of the bytes. A point counts as seen by a view when it lies in front of the camera and
projects within ``--margin`` of the frame's size around the frame (a Gaussian near the border
still reaches into it). The points are the scene's (COLMAP's sparse points, or a PLY's means with
``--ply``); the training views are those that ``cdcgs train`` would use. Printed: the per-view
share (mean, least, most) and, for each batch size, the mean share of the union of that many
distinct views drawn at random.
"""

from __future__ import annotations

import argparse
import json
import sys

import torch


def visible_masks(points: torch.Tensor, views, margin: float) -> torch.Tensor:
    """[V, P] bool: point p lies in front of view v's camera (depth > 0.01) and projects within
    ``margin`` x the frame's width and height around its frame."""
    homogeneous = torch.cat([points.double(), torch.ones(len(points), 1, dtype=torch.float64)], 1)
    masks = []
    for view in views:
        camera = (view.viewmat.double() @ homogeneous.T).T[:, :3]
        depth = camera[:, 2]
        pixel = (view.K.double() @ camera.T).T
        u = pixel[:, 0] / depth
        v = pixel[:, 1] / depth
        w, h = view.width, view.height
        inside = (u > -margin * w) & (u < (1 + margin) * w) & (v > -margin * h) & (v < (1 + margin) * h)
        masks.append((depth > 0.01) & inside)
    return torch.stack(masks)


def union_share(masks: torch.Tensor, batch: int, samples: int, generator: torch.Generator) -> float:
    """Mean share of the points that ``batch`` distinct random views see together, over ``samples`` draws."""
    shares = []
    for _ in range(samples):
        chosen = torch.randperm(len(masks), generator=generator)[:batch]
        shares.append(masks[chosen].any(0).double().mean().item())
    return sum(shares) / len(shares)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="scene folder")
    parser.add_argument("--images", default=None, help="image folder of the scene, e.g. images")
    parser.add_argument("--ply", default=None, help="a trained model whose means to count (else the scene's points)")
    parser.add_argument("--batch", type=int, nargs="+", default=[2, 4], help="views per step; default 2 4")
    parser.add_argument("--margin", type=float, default=0.15, help="of the frame's size around it; default 0.15")
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    if args.margin < 0 or args.samples < 1 or min(args.batch) < 1:
        parser.error("--margin must be >= 0, --samples and every --batch >= 1")
    from cdcgs.io import load_scene, read_ply

    scene = load_scene(args.data, images=args.images, load_images_now=False, progress=False)
    if max(args.batch) > len(scene.train):
        parser.error(f"--batch {max(args.batch)} is more than the scene's {len(scene.train)} training views")
    points = torch.as_tensor(read_ply(args.ply).means) if args.ply else scene.points
    masks = visible_masks(points, scene.train, args.margin)
    per_view = masks.double().mean(1)
    generator = torch.Generator().manual_seed(args.seed)
    result = {
        "points": len(points),
        "views": len(scene.train),
        "margin": args.margin,
        "per_view": {"mean": per_view.mean().item(), "min": per_view.min().item(), "max": per_view.max().item()},
        "union": {str(b): union_share(masks, b, args.samples, generator) for b in args.batch},
    }
    view = result["per_view"]
    print(f"{result['points']:,} points, {result['views']} training views, margin {args.margin}")
    print(f"one view sees {view['mean']:.1%} on average ({view['min']:.1%} to {view['max']:.1%})")
    for b, share in result["union"].items():
        print(f"{b} random views see {share:.1%} together")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
