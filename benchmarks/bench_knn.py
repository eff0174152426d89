"""Exact KNN timing: cdcgs (Warp) next to scipy's cKDTree on the CPU, and on the GPU alone.

    python benchmarks/bench_knn.py [--device cpu|cuda] [--sizes ...] [--k 3] [--out results.json]

Point sets: "uniform" in a unit cube, and "clustered" like a real scene: half the points in a
dense object (sigma 0.05), a quarter in a mid-size cluster (sigma 0.5), a quarter in a sparse
background (sigma 30, tens of times farther out). cdcgs times the whole call (bounds, Morton sort,
search) as the median of --iters runs after a warm-up; cKDTree (default settings) times its build
plus a query of k+1 neighbours (it returns the point itself first). Both results are compared.
"""

import argparse
import json
import statistics
import time

import numpy as np
import torch

from cdcgs.neighbors import knn


def make_points(kind: str, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "uniform":
        return rng.random((n, 3), dtype=np.float32)
    parts = [
        rng.normal(0.0, 0.05, (n // 2, 3)),
        rng.normal(1.0, 0.5, (n // 4, 3)),
        rng.normal(0.0, 30.0, (n - n // 2 - n // 4, 3)),
    ]
    return np.concatenate(parts).astype(np.float32)


def time_cdcgs(points: torch.Tensor, k: int, iters: int) -> tuple[float, torch.Tensor]:
    knn(points, k)  # warm-up: kernel compilation and allocator
    times = []
    for _ in range(iters):
        if points.is_cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        _, index = knn(points, k)
        if points.is_cuda:
            torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times), index


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument(
        "--sizes", type=int, nargs="+", default=None, help="point counts (default: CPU 100k 1M, GPU 1M 3M 10M)"
    )
    parser.add_argument(
        "--kinds", nargs="+", default=["uniform", "clustered"], choices=["uniform", "clustered"], help="point sets"
    )
    parser.add_argument("--k", type=int, default=3, help="neighbours per point")
    parser.add_argument("--iters", type=int, default=None, help="timed runs (default: CPU 3, GPU 20)")
    parser.add_argument("--no-kdtree", action="store_true", help="skip the cKDTree comparison")
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    args = parser.parse_args()
    on_gpu = args.device.startswith("cuda")
    sizes = args.sizes or ([1_000_000, 3_000_000, 10_000_000] if on_gpu else [100_000, 1_000_000])
    iters = args.iters or (20 if on_gpu else 3)
    machine = (
        torch.cuda.get_device_name(args.device) if on_gpu else f"CPU ({torch.get_num_threads()} threads for torch)"
    )
    rows = []
    for kind in args.kinds:
        for n in sizes:
            points = make_points(kind, n)
            ms, index = time_cdcgs(torch.from_numpy(points).to(args.device), args.k, iters)
            row = {"device": machine, "kind": kind, "n": n, "k": args.k, "cdcgs_ms": ms}
            if not args.no_kdtree and not on_gpu:
                from scipy.spatial import cKDTree

                t0 = time.perf_counter()
                _, kd_index = cKDTree(points).query(points, args.k + 1)
                row["ckdtree_ms"] = (time.perf_counter() - t0) * 1e3
                row["agree"] = float(np.mean(kd_index[:, 1:] == index.cpu().numpy()))
            rows.append(row)
            print(json.dumps(row), flush=True)
    print()
    print("| points | N | k | cdcgs ms | cKDTree ms | cdcgs / cKDTree |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        kd = f"{r['ckdtree_ms']:.1f}" if "ckdtree_ms" in r else "-"
        ratio = f"{r['cdcgs_ms'] / r['ckdtree_ms']:.2f}" if "ckdtree_ms" in r else "-"
        print(f"| {r['kind']} | {r['n']:,} | {r['k']} | {r['cdcgs_ms']:.1f} | {kd} | {ratio} |")
    print(f"device: {machine}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
