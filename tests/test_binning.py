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


def _rectangle(mean, radius, tiles_x, tiles_y):
    """Tiles [x0, x1) x [y0, y1) of a pixel-radius rectangle, as 3DGS bins."""
    x0 = int(torch.clamp(torch.floor((mean[0] - radius[0]) / TILE_SIZE), 0, tiles_x))
    x1 = int(torch.clamp(torch.floor((mean[0] + radius[0]) / TILE_SIZE) + 1, 0, tiles_x))
    y0 = int(torch.clamp(torch.floor((mean[1] - radius[1]) / TILE_SIZE), 0, tiles_y))
    y1 = int(torch.clamp(torch.floor((mean[1] + radius[1]) / TILE_SIZE) + 1, 0, tiles_y))
    return x0, x1, y0, y1


def _tiles_within(mean, conic, bound, width, height, rect):
    """Tiles of ``rect`` with a pixel centre where d^T conic d <= bound (float64 brute force)."""
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=torch.float64) + 0.5, torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij"
    )
    dx, dy = xs - mean[0], ys - mean[1]
    inside = conic[0] * dx * dx + 2 * conic[1] * dx * dy + conic[2] * dy * dy <= bound
    tx, ty = (xs[inside] // TILE_SIZE).long(), (ys[inside] // TILE_SIZE).long()
    x0, x1, y0, y1 = rect
    keep = (tx >= x0) & (tx < x1) & (ty >= y0) & (ty < y1)
    return set(zip(ty[keep].tolist(), tx[keep].tolist()))


def test_each_gaussian_is_listed_in_exactly_the_tiles_its_footprint_reaches(device):
    """A render bins each Gaussian into the tiles where it reaches alpha 1/255 at a pixel centre
    (d^T conic d <= 2 ln(255 opacity)), not its whole rectangle: every such tile is listed, and
    no tile where it stays clearly below; fewer pairs than rectangles."""
    width, height = 70, 45
    scene = make_scene(300, width, height, sh_degree=0, seed=14)
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=width, height=height
    )
    means2d, conics = info.means2d.detach().cpu().double(), info.conics.detach().cpu().double()
    opacities, radii = info.opacities.detach().cpu().double(), info.radii.cpu().double()
    counts, ids = info.tile_counts.cpu(), info.sorted_gauss_ids.cpu()
    tile_of_entry = torch.zeros(ids.numel(), dtype=torch.long)
    for tile, (start, end) in enumerate(info.tile_ranges.cpu().tolist()):
        tile_of_entry[start:end] = tile
    rectangles = 0
    for i in range(300):
        if not info.visible[i]:
            assert counts[i] == 0
            continue
        rect = _rectangle(means2d[i], radii[i], info.tiles_x, info.tiles_y)
        rectangles += (rect[1] - rect[0]) * (rect[3] - rect[2])
        bound = 2 * torch.log(opacities[i] * 255)
        listed = {divmod(t, info.tiles_x) for t in tile_of_entry[ids == i].tolist()}
        needed = _tiles_within(means2d[i], conics[i], bound, width, height, rect)
        allowed = _tiles_within(means2d[i], conics[i], bound + 0.05, width, height, rect)
        assert needed <= listed <= allowed, i
        assert counts[i] == len(listed)
    assert info.num_intersections < 0.95 * rectangles


def test_without_footprints_bin_gaussians_lists_whole_rectangles(device):
    """``bin_gaussians`` without conics and opacities: each Gaussian in every tile of its
    pixel-radius rectangle (the wp.launch user's choice when it has no conics)."""
    import warp as wp

    from cdcgs.kernels import bin_gaussians

    width, height = 70, 45
    scene = make_scene(300, width, height, sh_degree=0, seed=14)
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=width, height=height
    )
    bins = bin_gaussians(
        wp.from_torch(info.means2d.detach().contiguous(), dtype=wp.vec2),
        wp.from_torch(info.radii.contiguous(), dtype=wp.vec2i),
        wp.from_torch(info.depths.detach().contiguous()),
        width,
        height,
    )
    counts, ids = torch.from_numpy(bins.tile_counts.numpy()), torch.from_numpy(bins.sorted_gauss_ids.numpy())
    for i in range(300):
        rect = _rectangle(
            info.means2d[i].detach().cpu().double(), info.radii[i].cpu().double(), bins.tiles_x, bins.tiles_y
        )
        area = (rect[1] - rect[0]) * (rect[3] - rect[2]) if info.visible[i] else 0
        assert counts[i] == area == (ids == i).sum(), i
    with pytest.raises(ValueError, match="both conics and opacities"):
        bin_gaussians(
            wp.from_torch(info.means2d.detach().contiguous(), dtype=wp.vec2),
            wp.from_torch(info.radii.contiguous(), dtype=wp.vec2i),
            wp.from_torch(info.depths.detach().contiguous()),
            width,
            height,
            conics=wp.from_torch(info.conics.detach().contiguous(), dtype=wp.vec3),
        )


def test_a_thin_diagonal_gaussian_takes_its_diagonal_tiles_not_its_box(device):
    """A 1 px wide Gaussian along the image diagonal: its rectangle is every tile; its footprint
    crosses about three tiles per row of tiles."""
    import math

    import warp as wp

    from cdcgs.kernels import bin_gaussians

    size = 256
    # Covariance of a Gaussian with sigma 60 px along (1, 1) and 0.5 px across it.
    along, across = 60.0**2, 0.5**2
    a = c = (along + across) / 2
    b = (along - across) / 2
    det = a * c - b * b
    conic = [c / det, -b / det, a / det]
    opacity = 0.9
    extent = math.sqrt(2 * math.log(opacity * 255))
    radius = [math.ceil(extent * math.sqrt(a)), math.ceil(extent * math.sqrt(c))]
    array = lambda values, dtype: wp.array([values], dtype=dtype, device=device)
    common = (array([128.0, 128.0], wp.vec2), array(radius, wp.vec2i), wp.array([1.0], dtype=wp.float32, device=device))
    box = bin_gaussians(*common, size, size)
    exact = bin_gaussians(
        *common,
        size,
        size,
        conics=array(conic, wp.vec3),
        opacities=wp.array([opacity], dtype=wp.float32, device=device),
    )
    assert box.num_intersections == 16 * 16
    assert 16 <= exact.num_intersections <= 3 * 16, exact.num_intersections
    listed = {
        divmod(int(t), 16) for t in range(256) if exact.tile_ranges.numpy()[t, 1] > exact.tile_ranges.numpy()[t, 0]
    }
    assert {(k, k) for k in range(16)} <= listed, "the diagonal tiles"


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


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("width, height", [(90, 60), (128, 64)])
def test_binning_within_a_capacity_gives_the_same_lists_without_reading_the_count(device, exact, width, height):
    """``finish_binning_within``: the pairs in a fixed number of slots, no host read of the count.
    With room to spare or exactly enough, every tile's list equals ``finish_binning``'s and the
    overflow flag stays 0; one slot short, the flag is 1. 128 x 64 has 32 tiles, a power of two:
    the empty slots' key (32) needs a sort bit more than the tile ids."""
    import numpy as np
    import warp as wp

    from cdcgs.kernels.binning import finish_binning, finish_binning_within, start_binning

    rng = np.random.default_rng(11)
    n = 300
    means2d = rng.uniform(-20, [width + 20, height + 20], size=(n, 2)).astype(np.float32)
    radii = rng.integers(1, 25, size=(n, 2)).astype(np.int32)
    radii[rng.random(n) < 0.2] = 0
    depths = rng.choice(np.float32([0.5, 1.0, 3.0, 7.25]), size=n)
    conics = np.stack([rng.uniform(0.01, 0.2, n), rng.uniform(-0.005, 0.005, n), rng.uniform(0.01, 0.2, n)], 1)
    opacities = rng.uniform(0.01, 0.99, n)

    def start():
        footprint = {}
        if exact:
            footprint = {
                "conics": wp.array(conics.astype(np.float32), dtype=wp.vec3, device=device),
                "opacities": wp.array(opacities.astype(np.float32), dtype=wp.float32, device=device),
            }
        return start_binning(
            wp.array(means2d, dtype=wp.vec2, device=device),
            wp.array(radii, dtype=wp.vec2i, device=device),
            wp.array(depths, dtype=wp.float32, device=device),
            width,
            height,
            **footprint,
        )

    first = start()
    total = int(first.offsets.numpy()[-1])
    reference = finish_binning(first, total)
    ranges, ids = reference.tile_ranges.numpy(), reference.sorted_gauss_ids.numpy()
    assert total > 100
    for capacity in (total + 37, total):
        bins, overflow = finish_binning_within(start(), capacity)
        assert overflow.numpy().tolist() == [0] and bins.num_intersections == capacity
        got_ranges, got_ids = bins.tile_ranges.numpy(), bins.sorted_gauss_ids.numpy()
        np.testing.assert_array_equal(got_ranges, ranges)
        for begin, end in ranges:
            assert got_ids[begin:end].tolist() == ids[begin:end].tolist()
        assert (got_ids[total:] == -1).all() and len(got_ids) == capacity
    _, overflow = finish_binning_within(start(), total - 1)
    assert overflow.numpy().tolist() == [1]
    with pytest.raises(ValueError, match="capacity of at least 1"):
        finish_binning_within(start(), 0)
