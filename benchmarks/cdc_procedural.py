"""CDC-GS against the 3DGS rules on the procedural scene (CPU is enough): correlation and placement.

    python benchmarks/cdc_procedural.py [--iters 600] [--out outputs/cdc_procedural] [--device cpu]

Trains ``3dgs`` (with the Γ-Ψ correlation logged), ``cdc`` with the full schedule and ``cdc`` with
the online schedule on cdcgs's procedural garden-like scene, with 3DGS's schedule scaled to
``--iters`` as ``examples/train_garden.py`` does (denser schedules multiply the Gaussians of this
small scene until the CPU crawls), then prints for each run: the Pearson correlation of Γ and Ψ at the
last densification step, test PSNR, the number of Gaussians, and how many sit on the finely
textured objects (two spheres and a box) versus on the flat wall, by distance to each surface.
"""

import argparse
import json
import os

import numpy as np

from cdcgs.datasets import procedural
from cdcgs.io.ply import read_ply
from cdcgs.train import DataConfig, TrainConfig, Trainer
from cdcgs.train.outputs import correlation_curve

RUNS = {
    "3dgs": ("3dgs", {"log_correlation": True}),
    "cdc (full)": ("cdc", {"complexity_schedule": "full"}),
    "cdc (online)": ("cdc", {"complexity_schedule": "online"}),
}


def scaled_schedule(iters: int) -> dict:
    """examples/train_garden.py's procedural schedule (600 iterations: densify every 50 from 100 to
    450, no opacity reset) stretched to ``iters``."""
    return {
        "densify_from": iters // 6,
        "densify_until": 3 * iters // 4,
        "densify_every": max(iters // 12, 1),
        "reset_every": 10 * iters,
    }


def surface_counts(means: np.ndarray, tolerance: float = 0.05) -> dict:
    """Gaussians within ``tolerance`` of the objects' surfaces and of the wall plane."""
    on_object = np.zeros(len(means), dtype=bool)
    for center, radius, _ in procedural.SPHERES:
        on_object |= np.abs(np.linalg.norm(means - np.asarray(center), axis=-1) - radius) < tolerance
    lo, hi = (np.asarray(v) for v in procedural.BOX)
    outside = np.maximum(np.maximum(lo - means, means - hi), 0.0)
    inside = np.minimum(means - lo, hi - means).min(-1)
    box_distance = np.where((outside > 0).any(-1), np.linalg.norm(outside, axis=-1), inside)
    on_object |= box_distance < tolerance
    on_wall = (
        (np.abs(means[:, 2] - procedural.WALL_Z) < tolerance)
        & (np.abs(means[:, 0]) < 2.6)
        & (means[:, 1] > 0)
        & (means[:, 1] < 2.2)
    )
    return {"objects": int(on_object.sum()), "wall": int((on_wall & ~on_object).sum())}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--iters", type=int, default=600, help="iterations of each run (default: 600, as examples/train_garden.py)"
    )
    parser.add_argument("--out", default="outputs/cdc_procedural", help="folder for the scene and the runs")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every run (default: 0)")
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    args = parser.parse_args()
    scene = os.path.join(args.out, "scene")
    if not os.path.isdir(os.path.join(scene, "sparse")):
        procedural.make_procedural_scene(scene)
    rows = []
    for label, (strategy, options) in RUNS.items():
        out = os.path.join(args.out, label.replace(" ", "").replace("(", "-").replace(")", ""))
        config = TrainConfig(
            data=DataConfig(data=scene),
            out=out,
            strategy=strategy,
            iters=args.iters,
            device=args.device,
            seed=args.seed,
            sh_every=max(args.iters // 30, 1),
            eval_every=0,
            checkpoint_every=0,
            progress=args.progress,
            overwrite=True,
            save_renders=False,
        )
        result = Trainer(config, {**scaled_schedule(args.iters), **options}).run()
        with open(os.path.join(out, "history.json")) as f:
            steps, values = correlation_curve(json.load(f))
        means = read_ply(os.path.join(out, "point_cloud.ply")).means.numpy()
        row = {
            "run": label,
            "final_correlation": values[-1],
            "at_step": steps[-1],
            "psnr": result["test"]["psnr"],
            "lpips_vgg": result["test"]["lpips_vgg"],
            "lpips_alex": result["test"]["lpips_alex"],
            "gaussians": result["num_gaussians"],
            **surface_counts(means),
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(
        "\n| run | final r(Γ, Ψ) | test PSNR | LPIPS-VGG | LPIPS-Alex | Gaussians | on objects | on wall |"
        "\n|---|---|---|---|---|---|---|---|"
    )
    for r in rows:
        lpips = " | ".join("-" if r[key] is None else f"{r[key]:.3f}" for key in ("lpips_vgg", "lpips_alex"))
        print(
            f"| {r['run']} | {r['final_correlation']:.3f} (step {r['at_step']}) | {r['psnr']:.2f} | {lpips} | "
            f"{r['gaussians']} | {r['objects']} | {r['wall']} |"
        )
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
