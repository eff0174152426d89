"""Tile binning against brute force: every composited (pixel, Gaussian) pair is in the pixel's
tile list, and each tile's list is in depth order."""

import pytest
import reference
import torch
from conftest import make_scene

import cdcgs
from cdcgs.kernels import TILE_SIZE


@pytest.mark.parametrize("seed,n,width,height", [(11, 200, 50, 33), (12, 500, 83, 50), (13, 60, 16, 16)])
def test_tile_lists_hold_every_composited_pair_in_depth_order(device, seed, n, width, height):
    scene = make_scene(n, width, height, sh_degree=0, seed=seed)
    tensors = [t.to(device) for t in scene.tensors()]
    _, _, info = cdcgs.rasterize(*tensors, viewmat=scene.viewmat, K=scene.K, width=width, height=height)
    d = [t.double() for t in scene.tensors()]
    *_, weights = reference.render(*d, viewmat=scene.viewmat.double(), K=scene.K.double(), width=width, height=height)
    flat = info.tile_ranges.cpu()
    ids = info.sorted_gauss_ids.cpu().long()
    depths = info.depths.detach().cpu()
    tiles_y, tiles_x = -(-height // TILE_SIZE), -(-width // TILE_SIZE)
    assert (info.tiles_y, info.tiles_x) == (tiles_y, tiles_x)
    assert flat.shape == (tiles_y * tiles_x, 2)  # row-major tiles: ty * tiles_x + tx
    ranges = flat.view(tiles_y, tiles_x, 2)
    assert info.num_intersections == int(info.tile_counts.sum()) == ids.numel()
    # Ranges partition the sorted list in tile order.
    nonempty = flat[flat[:, 1] > flat[:, 0]]
    assert nonempty[0, 0] == 0 and nonempty[-1, 1] == ids.numel()
    assert (nonempty[1:, 0] == nonempty[:-1, 1]).all()
    # Brute-force tile membership of each Gaussian from its integer radii.
    checked_pairs = 0
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            start, end = ranges[ty, tx].tolist()
            tile_ids = ids[start:end]
            assert len(set(tile_ids.tolist())) == len(tile_ids), "a Gaussian listed twice in one tile"
            dz = depths[tile_ids]
            assert (dz[1:] >= dz[:-1]).all(), f"tile ({tx}, {ty}) not sorted by depth"
            equal = dz[1:] == dz[:-1]
            assert (tile_ids[1:][equal] > tile_ids[:-1][equal]).all(), "equal depths not in id order"
            position = {g: k for k, g in enumerate(tile_ids.tolist())}
            for y in range(ty * TILE_SIZE, min((ty + 1) * TILE_SIZE, height)):
                for x in range(tx * TILE_SIZE, min((tx + 1) * TILE_SIZE, width)):
                    composited = torch.nonzero(weights[y * width + x] > 0).flatten().tolist()
                    missing = [g for g in composited if g not in position]
                    assert not missing, f"pixel ({x}, {y}) composites {missing} missing from its tile list"
                    order = sorted(composited, key=lambda g: (depths[g].item(), g))
                    assert [position[g] for g in order] == sorted(position[g] for g in composited)
                    checked_pairs += len(composited)
    assert checked_pairs > 0


def test_tile_counts_match_rectangles(device):
    """Each Gaussian's tile count is the number of tiles its pixel-radius rectangle overlaps."""
    scene = make_scene(300, 70, 45, sh_degree=0, seed=14)
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=70, height=45
    )
    means2d = info.means2d.detach().cpu().double()
    radii = info.radii.cpu().double()
    counts = info.tile_counts.cpu()
    for i in range(300):
        if not info.visible[i]:
            assert counts[i] == 0
            continue
        x0 = int(torch.clamp(torch.floor((means2d[i, 0] - radii[i, 0]) / TILE_SIZE), 0, info.tiles_x))
        x1 = int(torch.clamp(torch.floor((means2d[i, 0] + radii[i, 0]) / TILE_SIZE) + 1, 0, info.tiles_x))
        y0 = int(torch.clamp(torch.floor((means2d[i, 1] - radii[i, 1]) / TILE_SIZE), 0, info.tiles_y))
        y1 = int(torch.clamp(torch.floor((means2d[i, 1] + radii[i, 1]) / TILE_SIZE) + 1, 0, info.tiles_y))
        assert counts[i] == (x1 - x0) * (y1 - y0), i
        listed = (info.sorted_gauss_ids.cpu() == i).sum()
        assert listed == counts[i]


def test_bin_gaussians_orders_each_tile_by_depth_then_id(device):
    """``bin_gaussians`` on plain Warp arrays against a brute-force sort: many equal depths (ties
    go to the lower id), culled Gaussians (radius 0), footprints clipped by the image border."""
    import numpy as np
    import warp as wp

    from cdcgs.kernels import bin_gaussians

    rng = np.random.default_rng(5)
    n, width, height = 400, 90, 60
    means2d = rng.uniform(-20, [110, 80], size=(n, 2)).astype(np.float32)
    radii = rng.integers(1, 30, size=(n, 2)).astype(np.int32)
    radii[rng.random(n) < 0.2] = 0
    depths = rng.choice(np.float32([0.5, 1.0, 1.0 + 2**-20, 3.0, 7.25]), size=n)
    bins = bin_gaussians(
        wp.array(means2d, dtype=wp.vec2, device=device),
        wp.array(radii, dtype=wp.vec2i, device=device),
        wp.array(depths, dtype=wp.float32, device=device),
        width,
        height,
    )
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    assert (bins.tiles_x, bins.tiles_y) == (tiles_x, tiles_y) and bins.tile_ranges.shape == (tiles_y * tiles_x, 2)
    ranges = bins.tile_ranges.numpy().reshape(tiles_y, tiles_x, 2)
    ids = bins.sorted_gauss_ids.numpy()
    counts = np.zeros(n, dtype=np.int64)
    ties = 0
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            listed = []
            for g in range(n):
                if radii[g].min() <= 0:
                    continue
                (mx, my), (rx, ry) = means2d[g].astype(np.float64), radii[g]
                x0, x1 = (
                    max(int(np.floor((mx - rx) / TILE_SIZE)), 0),
                    min(int(np.floor((mx + rx) / TILE_SIZE)) + 1, tiles_x),
                )
                y0, y1 = (
                    max(int(np.floor((my - ry) / TILE_SIZE)), 0),
                    min(int(np.floor((my + ry) / TILE_SIZE)) + 1, tiles_y),
                )
                if x0 <= tx < x1 and y0 <= ty < y1:
                    listed.append(g)
                    counts[g] += 1
            expected = sorted(listed, key=lambda g: (depths[g], g))
            ties += len(expected) - len({float(depths[g]) for g in expected})
            start, end = ranges[ty, tx]
            assert ids[start:end].tolist() == expected, (tx, ty)
    assert bins.num_intersections == counts.sum() == len(ids)
    assert (bins.tile_counts.numpy() == counts).all()
    assert ties > 0, "the scene must hold Gaussians of equal depth in one tile"
