"""Tile binning: which 16x16 pixel tiles each projected Gaussian touches, sorted by (tile, depth).

Pure Warp. ``bin_gaussians`` runs the whole sequence (count, prefix sum, keys, radix sort, tile
ranges) on Warp arrays; the kernels are public for callers that manage their own buffers.
"""

from dataclasses import dataclass
from typing import Callable

import warp as wp

TILE_SIZE = 16


@wp.func
def tile_rect(mean2d: wp.vec2, radius: wp.vec2i, tiles_x: int, tiles_y: int):
    """Tiles [x0, x1) x [y0, y1) holding every pixel centre within the Gaussian's radii."""
    fx = float(radius[0])
    fy = float(radius[1])
    x0 = wp.clamp(int(wp.floor((mean2d[0] - fx) / 16.0)), 0, tiles_x)
    x1 = wp.clamp(int(wp.floor((mean2d[0] + fx) / 16.0)) + 1, 0, tiles_x)
    y0 = wp.clamp(int(wp.floor((mean2d[1] - fy) / 16.0)), 0, tiles_y)
    y1 = wp.clamp(int(wp.floor((mean2d[1] + fy) / 16.0)) + 1, 0, tiles_y)
    return wp.vec4i(x0, x1, y0, y1)


@wp.kernel(enable_backward=False)
def count_tiles_kernel(
    means2d: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.vec2i),
    tiles_x: int,
    tiles_y: int,
    tile_counts_out: wp.array(dtype=wp.int32),
):
    """Number of tiles each Gaussian touches (0 for culled ones, whose radii are 0)."""
    i = wp.tid()
    r = radii[i]
    if r[0] <= 0 or r[1] <= 0:
        tile_counts_out[i] = 0
        return
    rect = tile_rect(means2d[i], r, tiles_x, tiles_y)
    tile_counts_out[i] = wp.max(rect[1] - rect[0], 0) * wp.max(rect[3] - rect[2], 0)


@wp.kernel(enable_backward=False)
def emit_keys_kernel(
    means2d: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.vec2i),
    depth_bits: wp.array(dtype=wp.int32),
    tile_offsets: wp.array(dtype=wp.int32),
    tiles_x: int,
    tiles_y: int,
    keys_out: wp.array(dtype=wp.int64),
    gauss_ids_out: wp.array(dtype=wp.int32),
):
    """One key per (tile, Gaussian): tile id in the high 32 bits, the depth's float bits below.

    Depths are positive, so their IEEE bits sort like the depths themselves. ``tile_offsets`` is
    the inclusive prefix sum of the tile counts.
    """
    i = wp.tid()
    r = radii[i]
    if r[0] <= 0 or r[1] <= 0:
        return
    rect = tile_rect(means2d[i], r, tiles_x, tiles_y)
    k = tile_offsets[i] - wp.max(rect[1] - rect[0], 0) * wp.max(rect[3] - rect[2], 0)
    low = wp.int64(depth_bits[i])
    for ty in range(rect[2], rect[3]):
        for tx in range(rect[0], rect[1]):
            keys_out[k] = (wp.int64(ty * tiles_x + tx) << wp.int64(32)) | low
            gauss_ids_out[k] = i
            k += 1


@wp.kernel(enable_backward=False)
def tile_ranges_kernel(
    sorted_keys: wp.array(dtype=wp.int64),
    num_intersections: int,
    tile_ranges_out: wp.array2d(dtype=wp.int32),
):
    """[start, end) of each tile's run in the sorted intersections (tiles with none keep 0, 0)."""
    k = wp.tid()
    tile = int(sorted_keys[k] >> wp.int64(32))
    if k == 0:
        tile_ranges_out[tile, 0] = 0
    else:
        previous = int(sorted_keys[k - 1] >> wp.int64(32))
        if previous != tile:
            tile_ranges_out[previous, 1] = k
            tile_ranges_out[tile, 0] = k
    if k == num_intersections - 1:
        tile_ranges_out[tile, 1] = num_intersections


@dataclass
class TileBins:
    """The result of :func:`bin_gaussians` (Warp arrays on the Gaussians' device)."""

    tiles_x: int
    tiles_y: int
    tile_counts: wp.array  # [N] int32, tiles touched by each Gaussian
    num_intersections: int
    gauss_ids: wp.array  # [num_intersections] int32, Gaussian ids sorted by (tile, depth)
    tile_ranges: wp.array  # [tiles_y * tiles_x, 2] int32, [start, end) into gauss_ids


def _warp_empty(shape, dtype, device):
    return wp.empty(shape, dtype=dtype, device=device)


def bin_gaussians(
    means2d: wp.array,
    radii: wp.array,
    depths: wp.array,
    width: int,
    height: int,
    allocate: Callable | None = None,
    zeros: Callable | None = None,
    read_count: Callable | None = None,
) -> TileBins:
    """Bin projected Gaussians into 16x16 tiles and sort each tile's list by depth.

    Args:
        means2d: [N] vec2 pixel means; radii: [N] vec2i per-axis pixel radii (0 = culled);
            depths: [N] float32 camera-space depths (> 0 for visible Gaussians).
        width, height: image size in pixels.
        allocate, zeros: optional ``(shape, dtype, device) -> wp.array`` allocators (the torch face
            passes ones backed by torch's caching allocator); default ``wp.empty`` / ``wp.zeros``.
        read_count: optional ``(tile_offsets) -> int`` reading the total intersection count.

    The one host synchronisation of a render happens here: the intersection count must be known
    on the host to size the sort buffers.
    """
    device = means2d.device
    allocate = allocate or _warp_empty
    zeros = zeros or (lambda shape, dtype, dev: wp.zeros(shape, dtype=dtype, device=dev))
    n = means2d.shape[0]
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    tile_counts = allocate((n,), wp.int32, device)
    wp.launch(count_tiles_kernel, n, inputs=[means2d, radii, tiles_x, tiles_y], outputs=[tile_counts], device=device)
    tile_offsets = allocate((n,), wp.int32, device)
    wp.utils.array_scan(tile_counts, tile_offsets, inclusive=True)
    if read_count is None:
        total = int(tile_offsets[n - 1 : n].numpy()[0])  # host sync: sizes the sort buffers
    else:
        total = int(read_count(tile_offsets))
    num_tiles = tiles_x * tiles_y
    tile_ranges = zeros((num_tiles, 2), wp.int32, device)
    # radix_sort_pairs needs twice the count as scratch.
    keys = allocate((max(2 * total, 2),), wp.int64, device)
    gauss_ids = allocate((max(2 * total, 2),), wp.int32, device)
    if total > 0:
        wp.launch(
            emit_keys_kernel,
            n,
            inputs=[means2d, radii, depths.view(wp.int32), tile_offsets, tiles_x, tiles_y],
            outputs=[keys, gauss_ids],
            device=device,
        )
        end_bit = 32 + max(int(num_tiles - 1).bit_length(), 1)
        wp.utils.radix_sort_pairs(keys, gauss_ids, total, end_bit=end_bit)
        wp.launch(tile_ranges_kernel, total, inputs=[keys, total], outputs=[tile_ranges], device=device)
    return TileBins(
        tiles_x=tiles_x,
        tiles_y=tiles_y,
        tile_counts=tile_counts,
        num_intersections=total,
        gauss_ids=gauss_ids[:total] if total > 0 else gauss_ids[:0],
        tile_ranges=tile_ranges,
    )
