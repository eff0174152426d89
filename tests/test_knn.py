"""Exact KNN against brute force (numpy, float64) on hard point distributions."""

import os

import numpy as np
import pytest
import torch

from cdcgs.neighbors import density, initial_scales, knn

BONSAI = os.environ.get("CDCGS_BONSAI", os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "bonsai"))


def brute_force(points: np.ndarray, k: int, queries: np.ndarray | None = None):
    """k nearest other points of each query index, float64, ties by the smaller index."""
    p = points.astype(np.float64)
    queries = np.arange(len(p)) if queries is None else queries
    dists, idxs = [], []
    for chunk in np.array_split(queries, max(1, len(queries) * len(p) // 2_000_000)):
        d2 = ((p[chunk, None, :] - p[None, :, :]) ** 2).sum(-1)
        d2[np.arange(len(chunk)), chunk] = np.inf
        # The k + 8 smallest by value, then exactly ordered by (distance, index) among those.
        m = min(k + 8, len(p) - 1)
        candidates = np.argpartition(d2, m, axis=-1)[:, : m + 1]
        cand_d = np.take_along_axis(d2, candidates, 1)
        order = np.lexsort((candidates, cand_d), axis=-1)[:, :k]
        idxs.append(np.take_along_axis(candidates, order, 1))
        dists.append(np.take_along_axis(cand_d, order, 1))
    return np.concatenate(dists), np.concatenate(idxs)


def assert_knn_equal(points, k, sqdist, index, queries=None):
    ref_d, ref_i = brute_force(points, k, queries)
    if queries is not None:
        sqdist, index = sqdist[queries], index[queries]
    np.testing.assert_allclose(sqdist, ref_d, rtol=1e-6, atol=0)
    # Indices equal, except between candidates whose float64 distances are within float32
    # rounding of each other (then either order is right, and the distances were checked above).
    mismatch = index != ref_i
    if mismatch.any():
        p = points.astype(np.float64)
        rows, cols = np.nonzero(mismatch)
        true_d = ((p[index[rows, cols]] - p[rows if queries is None else queries[rows]]) ** 2).sum(-1)
        near_tie = np.abs(true_d - ref_d[rows, cols]) <= 1e-6 * np.maximum(ref_d[rows, cols], 1e-30)
        assert near_tie.all(), f"{(~near_tie).sum()} neighbours differ from brute force, e.g. row {rows[~near_tie][0]}"
    # Exact ties are broken by the smaller index.
    for row in range(len(index)):
        for j in range(1, k):
            if sqdist[row, j] == sqdist[row, j - 1]:
                assert index[row, j] > index[row, j - 1]


def uniform(rng, n):
    return rng.random((n, 3)).astype(np.float32)


def clustered(rng, n):
    """Blobs at very different scales: a dense object, a mid cluster and a sparse far background."""
    parts = [
        rng.normal(0.0, 0.02, (n // 2, 3)),
        rng.normal([2.0, 0.5, -1.0], 0.3, (n // 4, 3)),
        rng.normal(0.0, 40.0, (n - n // 2 - n // 4, 3)),
    ]
    return np.concatenate(parts).astype(np.float32)


def duplicated(rng, n):
    base = rng.random((n // 4, 3)).astype(np.float32)
    return np.concatenate([base, base, base[: n // 8], rng.random((n - 2 * (n // 4) - n // 8, 3)).astype(np.float32)])


def collinear(rng, n):
    t = np.concatenate([np.arange(n // 2), rng.random(n - n // 2) * n])  # evenly spaced: exact ties
    return (np.stack([t, 2 * t, -t], -1) * 0.25 + 3.0).astype(np.float32)


def planar(rng, n):
    side = int(np.sqrt(n // 2))
    gx, gy = np.meshgrid(np.arange(side), np.arange(side))
    grid = np.stack([gx.ravel(), gy.ravel(), np.zeros(side * side)], -1) * 0.5  # exact ties on a grid
    rest = np.concatenate([rng.random((n - len(grid), 2)) * side * 0.5, np.zeros((n - len(grid), 1))], -1)
    return np.concatenate([grid, rest]).astype(np.float32)


DISTRIBUTIONS = {
    "uniform": uniform,
    "clustered": clustered,
    "duplicated": duplicated,
    "collinear": collinear,
    "planar": planar,
}


@pytest.mark.parametrize("name", DISTRIBUTIONS)
@pytest.mark.parametrize("k", [1, 3, 16])
def test_knn_matches_brute_force(device, name, k):
    rng = np.random.default_rng(len(name) * 100 + k)
    points = DISTRIBUTIONS[name](rng, 3000)
    sqdist, index = knn(torch.from_numpy(points).to(device), k)
    assert sqdist.shape == (3000, k) and index.shape == (3000, k) and sqdist.device.type == device
    assert_knn_equal(points, k, sqdist.cpu().numpy(), index.cpu().numpy())


def test_duplicates_are_at_distance_zero(device):
    points = np.repeat(np.random.default_rng(0).random((50, 3)).astype(np.float32), 5, axis=0)
    sqdist, index = knn(torch.from_numpy(points).to(device), 4)
    assert (sqdist == 0).all()
    # The four copies of point 5i are the other members of its group, in index order.
    expected = np.array([[j for j in range(5 * (i // 5), 5 * (i // 5) + 5) if j != i] for i in range(250)])
    np.testing.assert_array_equal(index.cpu().numpy(), expected)


def test_tiny_inputs(device):
    points = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 3.0, 0.0]], device=device)
    sqdist, index = knn(points, 2)
    np.testing.assert_array_equal(index.cpu().numpy(), [[1, 2], [0, 2], [0, 1]])
    np.testing.assert_allclose(sqdist.cpu().numpy(), [[1, 9], [1, 10], [9, 10]])


@pytest.mark.skipif(not os.path.isdir(BONSAI), reason="the bonsai scene is absent (set CDCGS_BONSAI)")
def test_knn_on_bonsai_points(device):
    import pycolmap

    reconstruction = pycolmap.Reconstruction(os.path.join(BONSAI, "sparse", "0"))
    points = np.array([p.xyz for p in reconstruction.points3D.values()], dtype=np.float32)
    assert len(points) > 100_000
    sqdist, index = knn(torch.from_numpy(points).to(device), 3)
    queries = np.random.default_rng(0).choice(len(points), 2000, replace=False)
    assert_knn_equal(points, 3, sqdist.cpu().numpy(), index.cpu().numpy(), queries)


@pytest.mark.parametrize(
    "points,k,match",
    [
        (torch.zeros(0, 3), 3, "points is empty"),
        (torch.rand(3, 3), 3, "k=3 needs at least k\\+1 points"),
        (torch.rand(10, 3), 0, "k must be an int in 1..16"),
        (torch.rand(40, 3), 17, "k must be an int in 1..16"),
        (torch.rand(10, 3).double(), 3, "points must be float32"),
        (torch.rand(10, 2), 3, "points must have shape \\[N, 3\\]"),
        (
            torch.tensor([[0.0, 0.0, 0.0], [1.0, float("nan"), 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]]),
            2,
            "1 point\\(s\\) with NaN or infinite",
        ),
        (
            torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, float("inf")], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]]),
            2,
            "NaN or infinite",
        ),
    ],
)
def test_bad_input(device, points, k, match):
    with pytest.raises(ValueError, match=match):
        knn(points.to(device), k)


def test_knn_search_on_warp_arrays(device):
    """``cdcgs.kernels.knn_search``, the plain-Warp entry, fills caller-given outputs with what the
    torch face returns."""
    import warp as wp

    from cdcgs.kernels import knn_search

    points = clustered(np.random.default_rng(3), 1000)
    sqdist = wp.empty((1000, 4), dtype=float, device=device)
    index = wp.empty((1000, 4), dtype=wp.int32, device=device)
    returned = knn_search(wp.array(points, dtype=wp.vec3, device=device), 4, sqdist_out=sqdist, index_out=index)
    assert returned[0] is sqdist and returned[1] is index
    assert_knn_equal(points, 4, sqdist.numpy(), index.numpy())
    _, torch_index = knn(torch.from_numpy(points).to(device), 4)
    np.testing.assert_array_equal(index.numpy(), torch_index.cpu().numpy())
    with pytest.raises(ValueError, match="1-D Warp array of vec3"):
        knn_search(wp.array(points[:, 0], dtype=float, device=device), 4)


def test_initial_scales_and_density(device):
    rng = np.random.default_rng(5)
    points = clustered(rng, 2000)
    ref_d, _ = brute_force(points, 3)
    t = torch.from_numpy(points).to(device)
    np.testing.assert_allclose(
        initial_scales(t, "3dgs").cpu().numpy(), np.sqrt(np.maximum(ref_d.mean(1), 1e-7)), rtol=1e-5
    )
    geometric = np.cbrt(ref_d.prod(1))
    np.testing.assert_allclose(initial_scales(t, "cdc").cpu().numpy(), np.sqrt(np.maximum(geometric, 1e-7)), rtol=1e-5)
    np.testing.assert_allclose(density(t).cpu().numpy(), 1.0 / (np.maximum(geometric, 1e-7) + 1e-6), rtol=1e-5)
    # Duplicates: zero distances give the floors.
    dup = torch.zeros(5, 3, device=device)
    assert torch.allclose(initial_scales(dup, "cdc").cpu(), torch.full((5,), 1e-7**0.5))
    assert torch.allclose(initial_scales(dup, "3dgs").cpu(), torch.full((5,), 1e-7**0.5))
    assert torch.allclose(density(dup).cpu(), torch.full((5,), 1 / 1.1e-6))
    with pytest.raises(ValueError, match="rule must be"):
        initial_scales(t, "mean")
