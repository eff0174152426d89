"""How far the poses of a scene made by ``cdcgs process`` are from a reference model of the same
photos, and, given a training of each, where the test PSNR is lost.

    python benchmarks/process_poses.py --reference ../shared/data/bonsai --processed bonsai_processed \
        [--runs RUN_ON_REFERENCE RUN_ON_PROCESSED]

The camera centres of the views the two models share (by image name) are mapped onto the
reference's by the best similarity (``cdcgs.geometry.similarity_transform``); printed: the centre
errors as a share of the reference cameras' spread (the largest distance from their mean), the
rotation errors after the same alignment, the breaks (consecutive views by name whose step
between camera centres points elsewhere, or is of another length, than the reference's: where a
model's parts were placed apart), and with ``--runs`` (two ``cdcgs train`` folders, their
metrics.json with per-view test results) the views that lose the most PSNR, with their pose errors.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys

import torch

from cdcgs.geometry import similarity_transform
from cdcgs.io import load_scene


def poses(path: str) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Image name -> (camera centre, world-to-camera rotation), float64, of every view of a scene."""
    scene = load_scene(path, test_every=0, load_images_now=False, progress=False)
    out = {}
    for view in scene.train:
        w2c = view.viewmat.double()
        rotation = w2c[:3, :3]
        out[view.name] = (-rotation.T @ w2c[:3, 3], rotation)
    return out


def compare(reference: dict, processed: dict) -> dict[str, tuple[float, float]]:
    """Image name -> (centre error / reference spread, rotation error in degrees) of the shared views."""
    names = sorted(set(reference) & set(processed))
    if len(names) < 3:
        raise SystemExit(f"the two models share {len(names)} image names; at least 3 are needed")
    ours = torch.stack([processed[n][0] for n in names])
    theirs = torch.stack([reference[n][0] for n in names])
    scale, rotation, shift = similarity_transform(ours, theirs)
    spread = (theirs - theirs.mean(0)).norm(dim=1).max()
    centre = ((scale * ours @ rotation.T + shift - theirs).norm(dim=1) / spread).tolist()
    out = {}
    for name, error in zip(names, centre):
        # The processed camera's world rotation carried into the reference frame, against the reference's.
        relative = (rotation @ processed[name][1].T).T @ reference[name][1].T
        cosine = ((torch.trace(relative) - 1) / 2).clamp(-1.0, 1.0)
        out[name] = (error, float(torch.rad2deg(torch.arccos(cosine))))
    return out


def breaks(reference: dict, processed: dict, angle: float = 20.0, factor: float = 2.0) -> list[tuple]:
    """(name, next name, direction error in degrees, length ratio over the median ratio) of each
    pair of consecutive shared views (sorted by name) whose step between centres, turned into the
    reference frame by the rotation the two models' camera rotations agree on, differs from the
    reference's step by more than ``angle`` degrees or ``factor`` in length. Photos taken in
    sequence, named in order, give steps that agree everywhere but where the model broke."""
    names = sorted(set(reference) & set(processed))
    # R_ref = R_proc W^T for a model turned by W: W is the mean of R_ref^T R_proc, made a rotation.
    mean = torch.stack([reference[n][1].T @ processed[n][1] for n in names]).mean(0)
    u, _, vt = torch.linalg.svd(mean)
    turn = u @ vt
    steps = []
    for first, second in itertools.pairwise(names):
        ours = turn @ (processed[second][0] - processed[first][0])
        theirs = reference[second][0] - reference[first][0]
        cosine = float(ours @ theirs / (ours.norm() * theirs.norm()).clamp_min(1e-12))
        steps.append(
            (
                first,
                second,
                math.degrees(math.acos(max(-1.0, min(1.0, cosine)))),
                float(ours.norm() / theirs.norm().clamp_min(1e-12)),
            )
        )
    median = float(torch.tensor([s[3] for s in steps]).median()) if steps else 1.0
    return [
        (first, second, error, ratio / median)
        for first, second, error, ratio in steps
        if error > angle or not 1.0 / factor <= ratio / median <= factor
    ]


def per_view_psnr(run: str) -> dict[str, float]:
    path = os.path.join(run, "metrics.json")
    if not os.path.isfile(path):
        raise SystemExit(f"--runs {run!r}: no metrics.json (a finished cdcgs train folder is needed)")
    with open(path) as f:
        return {view["name"]: view["psnr"] for view in json.load(f)["per_view"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", required=True, help="scene folder of the reference model")
    parser.add_argument("--processed", required=True, help="scene folder written by cdcgs process")
    parser.add_argument("--runs", nargs=2, metavar=("REFERENCE_RUN", "PROCESSED_RUN"), help="trainings of each")
    parser.add_argument("--worst", type=int, default=7, help="views listed with --runs")
    args = parser.parse_args(argv)
    reference_poses, processed_poses = poses(args.reference), poses(args.processed)
    errors = compare(reference_poses, processed_poses)
    centre = torch.tensor([e[0] for e in errors.values()]) * 100
    angle = torch.tensor([e[1] for e in errors.values()])
    print(f"{len(errors)} views in both models")
    print(
        f"centre error, % of the reference cameras' spread: median {centre.median():.2f}, "
        f"90th percentile {centre.quantile(0.9):.2f}, RMS {centre.pow(2).mean().sqrt():.2f}, "
        f"max {centre.max():.2f}; over 5%: {int((centre > 5).sum())} views"
    )
    print(f"rotation error, degrees: median {angle.median():.2f}, mean {angle.mean():.2f}, max {angle.max():.2f}")
    found = breaks(reference_poses, processed_poses)
    print(f"breaks between consecutive views (step off by > 20 degrees or 2x in length): {len(found)}")
    for first, second, error, ratio in found:
        print(f"  {first} -> {second}: direction {error:.1f} degrees off, length {ratio:.2f}x")
    if args.runs:
        reference, processed = (per_view_psnr(run) for run in args.runs)
        names = sorted(set(reference) & set(processed) & set(errors))
        if not names:
            raise SystemExit("--runs: the two runs share no test view that both models hold")
        loss = {n: reference[n] - processed[n] for n in names}
        mean = sum(loss.values()) / len(loss)
        print(
            f"\n{len(names)} test views: mean PSNR loss {mean:.2f} dB, median {torch.tensor(list(loss.values())).median():.2f} dB"
        )
        print("| view | PSNR reference | PSNR processed | loss | centre error | rotation error |")
        print("|---|---|---|---|---|---|")
        worst = sorted(names, key=lambda n: -loss[n])[: args.worst]
        for n in worst:
            print(
                f"| {n} | {reference[n]:.2f} | {processed[n]:.2f} | {loss[n]:.2f} | "
                f"{100 * errors[n][0]:.1f}% | {errors[n][1]:.2f}° |"
            )
        far = [n for n in names if errors[n][0] > 0.10]
        share = sum(loss[n] for n in far) / len(names)
        print(f"\nviews with centres off by more than 10%: {len(far)}, {share:.2f} dB of the mean loss")
    return 0


if __name__ == "__main__":
    sys.exit(main())
