"""Tile binning: which TILE_SIZE x TILE_SIZE (16 x 16) pixel tiles each projected Gaussian
touches, sorted by (tile, depth).

Pure Warp. ``bin_gaussians`` runs the whole sequence (depth sort, count, prefix sum, keys, sort by
tile, tile ranges) on Warp arrays; the kernels stay importable from this module for callers that
manage their own buffers.

A Gaussian's tiles are those of its bounding rectangle (the projection's per-axis radii) or, when
``bin_gaussians`` gets its conic and opacity, only those whose pixel centres its footprint reaches:
per row of tiles, the span that the ellipse {d : opacity * exp(-d^T conic d / 2) >= 1/255} covers
(the pixels the blend composites), so a thin diagonal Gaussian no longer claims its whole box.
The blend skips those pixels anyway: the image and its gradients do not change, only the work.

Tiles are numbered row-major, ``tile = tile_y * tiles_x + tile_x``, and the tile ranges are one
[tiles_y * tiles_x, 2] int32 array indexed by that number: ``[start, end)`` of each tile's run in
the sorted Gaussian ids.
"""

from collections.abc import Callable
from dataclasses import dataclass

import warp as wp

from ._constants import TILE_SIZE
from .projection import ALPHA_THRESHOLD

__all__ = [
    "BinningStart",
    "TileBins",
    "bin_gaussians",
    "count_tiles_kernel",
    "emit_keys_kernel",
    "finish_binning",
    "finish_binning_within",
    "gather_counts_kernel",
    "overflow_kernel",
    "row_span",
    "start_binning",
    "tile_ranges_kernel",
]

# Added to the footprint's bound 2 ln(opacity / (1/255)) so that rounding (and CUDA's fast exp in
# the blend) never loses a pixel on its edge: a few thousandths of a pixel wider.
SPAN_MARGIN = wp.constant(1.0e-3)


@wp.func
def tile_rect(mean2d: wp.vec2, radius: wp.vec2i, tiles_x: int, tiles_y: int):
    """Tiles [x0, x1) x [y0, y1) holding every pixel centre within the Gaussian's radii."""
    fx = float(radius[0])
    fy = float(radius[1])
    side = wp.static(float(TILE_SIZE))
    x0 = wp.clamp(int(wp.floor((mean2d[0] - fx) / side)), 0, tiles_x)
    x1 = wp.clamp(int(wp.floor((mean2d[0] + fx) / side)) + 1, 0, tiles_x)
    y0 = wp.clamp(int(wp.floor((mean2d[1] - fy) / side)), 0, tiles_y)
    y1 = wp.clamp(int(wp.floor((mean2d[1] + fy) / side)) + 1, 0, tiles_y)
    return wp.vec4i(x0, x1, y0, y1)


# Culled Gaussians sort after every visible one (positive float bits are below 0x7f800000).
CULLED_DEPTH_KEY = wp.constant(0x7FFFFFFF)


@wp.func
def rect_area(rect: wp.vec4i):
    return wp.max(rect[1] - rect[0], 0) * wp.max(rect[3] - rect[2], 0)


@wp.func
def footprint_bound(opacity: float) -> float:
    """t with {d : d^T conic d <= t} holding every pixel where opacity * exp(-d^T conic d / 2)
    reaches 1/255 (with SPAN_MARGIN)."""
    return 2.0 * wp.log(wp.max(opacity / ALPHA_THRESHOLD, 1.0)) + SPAN_MARGIN


@wp.func
def row_span(mean2d: wp.vec2, conic: wp.vec3, bound: float, ty: int, rect: wp.vec4i):
    """Tiles [x0, x1) of tile row ``ty`` (within ``rect``) holding a pixel centre of the ellipse
    d^T conic d <= bound around ``mean2d``; x0 >= x1 when it holds none.

    Over the row's band of pixel-centre heights, the ellipse's right edge is concave in the height
    and its left edge convex: their extremes sit at the ellipse's rightmost and leftmost points,
    clamped into the band."""
    side = wp.static(float(TILE_SIZE))
    a = conic[0]
    b = conic[1]
    c = conic[2]
    det = a * c - b * b
    lo = float(ty) * side + 0.5 - mean2d[1]  # the band of pixel-centre heights, about the mean
    hi = lo + side - 1.0
    reach = wp.sqrt(bound * a / det)  # |dy| of the ellipse's top and bottom
    lo = wp.max(lo, -reach)
    hi = wp.min(hi, reach)
    if lo > hi:
        return wp.vec2i(0, 0)
    peak = -b * wp.sqrt(bound / (c * det))  # dy of the rightmost point; the leftmost is at -peak
    yr = wp.clamp(peak, lo, hi)
    yl = wp.clamp(-peak, lo, hi)
    right = mean2d[0] + (-b * yr + wp.sqrt(wp.max(a * bound - det * yr * yr, 0.0))) / a
    left = mean2d[0] + (-b * yl - wp.sqrt(wp.max(a * bound - det * yl * yl, 0.0))) / a
    # Tile tx holds the pixel centres tx * side + 0.5 ... tx * side + side - 0.5.
    x0 = wp.max(int(wp.ceil((left - side + 0.5) / side)), rect[0])
    x1 = wp.min(int(wp.floor((right - 0.5) / side)) + 1, rect[1])
    return wp.vec2i(x0, x1)


@wp.func
def tiles_touched(mean2d: wp.vec2, conic: wp.vec3, bound: float, rect: wp.vec4i) -> int:
    """Tiles of ``rect`` in the footprint's row spans."""
    count = int(0)
    for ty in range(rect[2], rect[3]):
        span = row_span(mean2d, conic, bound, ty, rect)
        count += wp.max(span[1] - span[0], 0)
    return count


@wp.kernel(enable_backward=False)
def count_tiles_kernel(
    means2d: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.vec2i),
    depth_bits: wp.array(dtype=wp.int32),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=wp.float32),
    exact: int,
    tiles_x: int,
    tiles_y: int,
    tile_counts_out: wp.array(dtype=wp.int32),
    tile_rects_out: wp.array(dtype=wp.vec4i),
    depth_keys_out: wp.array(dtype=wp.int32),
    ids_out: wp.array(dtype=wp.int32),
):
    """Per Gaussian: the tiles it touches (count and bounding rectangle, 0 for culled ones, whose
    radii are 0; with ``exact`` only the tiles of its footprint's row spans, which needs
    ``conics`` and ``opacities``, else they may be None) and the keys of the depth sort: the
    depth's float bits (positive floats sort like their bits), culled Gaussians last, with
    ``ids_out[i] = i``."""
    i = wp.tid()
    r = radii[i]
    rect = wp.vec4i(0, 0, 0, 0)
    key = CULLED_DEPTH_KEY
    count = int(0)
    if r[0] > 0 and r[1] > 0:
        rect = tile_rect(means2d[i], r, tiles_x, tiles_y)
        key = depth_bits[i]
        if exact != 0:
            count = tiles_touched(means2d[i], conics[i], footprint_bound(opacities[i]), rect)
        else:
            count = rect_area(rect)
    tile_counts_out[i] = count
    tile_rects_out[i] = rect
    depth_keys_out[i] = key
    ids_out[i] = i


@wp.kernel(enable_backward=False)
def gather_counts_kernel(
    tile_counts: wp.array(dtype=wp.int32),
    depth_order: wp.array(dtype=wp.int32),
    ordered_counts_out: wp.array(dtype=wp.int32),
):
    """The tile counts in depth order, for the prefix sum that places each Gaussian's pairs."""
    j = wp.tid()
    ordered_counts_out[j] = tile_counts[depth_order[j]]


@wp.kernel(enable_backward=False)
def emit_keys_kernel(
    ordered_offsets: wp.array(dtype=wp.int32),
    num_gaussians: int,
    depth_order: wp.array(dtype=wp.int32),
    tile_rects: wp.array(dtype=wp.vec4i),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=wp.float32),
    exact: int,
    tiles_x: int,
    sentinel: int,
    keys_out: wp.array(dtype=wp.int32),
    gauss_ids_out: wp.array(dtype=wp.int32),
):
    """One thread per (tile id, Gaussian) pair, launched over all pairs: pair ``k`` belongs to the
    first Gaussian (in depth order) whose inclusive offset ``ordered_offsets`` exceeds ``k``, and
    is that Gaussian's ``r``-th tile in row-major order of its footprint (as ``count_tiles_kernel``
    counted them, with the same ``exact``).

    The pairs come out ordered by depth, so a stable sort by tile id then leaves each tile's list in
    depth order. One thread per pair, rather than one per Gaussian writing all of its pairs, keeps
    a warp's work even: a Gaussian over hundreds of tiles no longer holds up the 31 small ones that
    share its warp. The search for the Gaussian is a binary search whose first steps every thread
    shares (cached), and the threads of one Gaussian walk the same rows together.

    Launched over more slots than pairs (:func:`finish_binning_within`), a slot past the last
    pair gets the key ``sentinel`` (the tile count: it sorts after every tile) and the id -1.
    """
    k = wp.tid()
    if num_gaussians == 0:
        keys_out[k] = sentinel
        gauss_ids_out[k] = -1
        return
    if k >= ordered_offsets[num_gaussians - 1]:
        keys_out[k] = sentinel
        gauss_ids_out[k] = -1
        return
    lo = int(0)
    hi = num_gaussians - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if ordered_offsets[mid] > k:
            hi = mid
        else:
            lo = mid + 1
    start = int(0)
    if lo > 0:
        start = ordered_offsets[lo - 1]
    r = k - start
    g = depth_order[lo]
    rect = tile_rects[g]
    key = int(0)
    if exact != 0:
        mean2d = means2d[g]
        conic = conics[g]
        bound = footprint_bound(opacities[g])
        for ty in range(rect[2], rect[3]):
            span = row_span(mean2d, conic, bound, ty, rect)
            width = wp.max(span[1] - span[0], 0)
            if r < width:
                key = ty * tiles_x + span[0] + r
                break
            r -= width
    else:
        width = rect[1] - rect[0]
        key = (rect[2] + r // width) * tiles_x + rect[0] + r % width
    keys_out[k] = key
    gauss_ids_out[k] = g


@wp.kernel(enable_backward=False)
def tile_ranges_kernel(
    sorted_keys: wp.array(dtype=wp.int32),
    num_intersections: int,
    sentinel: int,
    tile_ranges_out: wp.array2d(dtype=wp.int32),
):
    """[start, end) of each tile's run in the sorted intersections (tiles with none keep 0, 0);
    ``tile_ranges_out`` is [tiles_y * tiles_x, 2], zeroed before. Keys equal to ``sentinel``
    (the empty slots of :func:`finish_binning_within`, sorted last) belong to no tile."""
    k = wp.tid()
    tile = sorted_keys[k]
    if tile == sentinel:
        if k > 0:
            previous = sorted_keys[k - 1]
            if previous != sentinel:
                tile_ranges_out[previous, 1] = k
        return
    if k == 0:
        tile_ranges_out[tile, 0] = 0
    else:
        previous = sorted_keys[k - 1]
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
    sorted_gauss_ids: wp.array  # [num_intersections] int32, Gaussian ids sorted by (tile, depth)
    # [tiles_y * tiles_x, 2] int32, [start, end) into sorted_gauss_ids of tile ty * tiles_x + tx
    tile_ranges: wp.array


def _warp_empty(shape, dtype, device):
    return wp.empty(shape, dtype=dtype, device=device)


@dataclass
class BinningStart:
    """The first half of :func:`bin_gaussians`, queued up to the prefix sum of the tile counts:
    what :func:`finish_binning` needs once the total intersection count, ``offsets[-1]``, has
    been read on the host. Made by :func:`start_binning`."""

    offsets: wp.array  # [N] int32, inclusive prefix sum of the tile counts in depth order
    tile_counts: wp.array
    tile_rects: wp.array
    depth_order: wp.array
    means2d: wp.array
    conics: wp.array | None
    opacities: wp.array | None
    tiles_x: int
    tiles_y: int
    device: wp.Device
    allocate: Callable
    zeros: Callable
    launch: Callable


def start_binning(
    means2d: wp.array,
    radii: wp.array,
    depths: wp.array,
    width: int,
    height: int,
    allocate: Callable | None = None,
    zeros: Callable | None = None,
    *,
    conics: wp.array | None = None,
    opacities: wp.array | None = None,
    launch: Callable | None = None,
) -> BinningStart:
    """Queue the first half of :func:`bin_gaussians` (same arguments, less ``read_count``): the
    tile counts, the depth order and their prefix sum. Nothing is read back, so a caller with
    several views may queue the next view's first half before it reads this one's count
    (:func:`cdcgs.render.start_bin_view`)."""
    device = means2d.device
    if (conics is None) != (opacities is None):
        raise ValueError("bin_gaussians: give both conics and opacities (exact footprints) or neither")
    exact = int(conics is not None)
    allocate = allocate or _warp_empty
    launch = launch or wp.launch
    zeros = zeros or (lambda shape, dtype, dev: wp.zeros(shape, dtype=dtype, device=dev))
    n = means2d.shape[0]
    tiles_x = (width + TILE_SIZE - 1) // TILE_SIZE
    tiles_y = (height + TILE_SIZE - 1) // TILE_SIZE
    # Two short sorts instead of one long one: the Gaussians by depth (N keys of 31 bits, 4 radix
    # passes), then their (tile, Gaussian) pairs, emitted in that depth order, by tile id alone with
    # a stable sort (13 bits for a 1297 x 840 image: 2 passes over 8-byte pairs). One sort of 64-bit
    # (tile, depth) keys takes 6 passes over 12-byte pairs; with 2.5 pairs per Gaussian the two
    # move 40% of its bytes for the same order. radix_sort_pairs needs twice the count as scratch.
    tile_counts = allocate((n,), wp.int32, device)
    tile_rects = allocate((n,), wp.vec4i, device)
    depth_keys = allocate((2 * n,), wp.int32, device)
    depth_order = allocate((2 * n,), wp.int32, device)
    launch(
        count_tiles_kernel,
        n,
        inputs=[means2d, radii, depths.view(wp.int32), conics, opacities, exact, tiles_x, tiles_y],
        outputs=[tile_counts, tile_rects, depth_keys, depth_order],
        device=device,
    )
    wp.utils.radix_sort_pairs(depth_keys, depth_order, n, end_bit=31)
    ordered_counts = depth_keys[:n]  # the sorted depth keys are spent: their buffer takes the counts
    launch(gather_counts_kernel, n, inputs=[tile_counts, depth_order], outputs=[ordered_counts], device=device)
    ordered_offsets = allocate((n,), wp.int32, device)
    wp.utils.array_scan(ordered_counts, ordered_offsets, inclusive=True)
    return BinningStart(
        offsets=ordered_offsets,
        tile_counts=tile_counts,
        tile_rects=tile_rects,
        depth_order=depth_order,
        means2d=means2d,
        conics=conics,
        opacities=opacities,
        tiles_x=tiles_x,
        tiles_y=tiles_y,
        device=device,
        allocate=allocate,
        zeros=zeros,
        launch=launch,
    )


def finish_binning(start: BinningStart, total: int) -> TileBins:
    """The second half of :func:`bin_gaussians`: the (tile, Gaussian) pairs emitted in depth order
    and sorted by tile, with ``total`` the intersection count, ``start.offsets[-1]``, read on the
    host."""
    num_tiles = start.tiles_x * start.tiles_y
    if total > 0:  # keys below the tile count: no sentinel (-1 matches none)
        return _emit_sorted(start, total, -1, max(int(num_tiles - 1).bit_length(), 1))
    keys = start.allocate((2,), wp.int32, start.device)
    return TileBins(
        tiles_x=start.tiles_x,
        tiles_y=start.tiles_y,
        tile_counts=start.tile_counts,
        num_intersections=0,
        sorted_gauss_ids=keys[:0],
        tile_ranges=start.zeros((num_tiles, 2), wp.int32, start.device),
    )


def _emit_sorted(start: BinningStart, slots: int, sentinel: int, end_bit: int) -> TileBins:
    """The pairs emitted into ``slots`` slots (an empty slot gets the key ``sentinel``), sorted by
    tile over ``end_bit`` bits, and each tile's range."""
    n = start.offsets.shape[0]
    device, launch = start.device, start.launch
    exact = int(start.conics is not None)
    num_tiles = start.tiles_x * start.tiles_y
    tile_ranges = start.zeros((num_tiles, 2), wp.int32, device)
    keys = start.allocate((2 * slots,), wp.int32, device)  # radix_sort_pairs needs twice the count
    gauss_ids = start.allocate((2 * slots,), wp.int32, device)
    launch(
        emit_keys_kernel,
        slots,
        inputs=[
            start.offsets,
            n,
            start.depth_order,
            start.tile_rects,
            start.means2d,
            start.conics,
            start.opacities,
            exact,
            start.tiles_x,
            sentinel,
        ],
        outputs=[keys, gauss_ids],
        device=device,
    )
    wp.utils.radix_sort_pairs(keys, gauss_ids, slots, end_bit=end_bit)
    launch(tile_ranges_kernel, slots, inputs=[keys, slots, sentinel], outputs=[tile_ranges], device=device)
    return TileBins(
        tiles_x=start.tiles_x,
        tiles_y=start.tiles_y,
        tile_counts=start.tile_counts,
        num_intersections=slots,
        sorted_gauss_ids=gauss_ids[:slots],
        tile_ranges=tile_ranges,
    )


@wp.kernel(enable_backward=False)
def overflow_kernel(
    ordered_offsets: wp.array(dtype=wp.int32),
    num_gaussians: int,
    capacity: int,
    overflow_out: wp.array(dtype=wp.int32),
):
    """``overflow_out[0]`` = 1 when the pairs (the last inclusive offset) exceed ``capacity``."""
    total = int(0)
    if num_gaussians > 0:
        total = ordered_offsets[num_gaussians - 1]
    overflow_out[0] = wp.where(total > capacity, 1, 0)


def finish_binning_within(start: BinningStart, capacity: int) -> tuple[TileBins, wp.array]:
    """:func:`finish_binning` without reading the intersection count on the host: the pairs go
    into ``capacity`` slots, and the empty slots (key ``sentinel`` = the tile count, id -1) sort
    after every pair and belong to no tile. Returns the bins (``sorted_gauss_ids`` of length
    ``capacity``; ``num_intersections`` is ``capacity``, an upper bound) and a [1] int32 device
    flag that is 1 when the count exceeded ``capacity``: then the bins miss pairs and a render
    from them is wrong, so whoever reads the flag later must discard it. With ``capacity`` at
    least the count, the tile ranges and each tile's list are those of :func:`finish_binning`
    (the sort is stable and the empty slots come last). The sort's work grows with ``capacity``.
    """
    if capacity < 1:
        raise ValueError(f"finish_binning_within needs a capacity of at least 1, got {capacity}")
    n = start.offsets.shape[0]
    overflow = start.allocate((1,), wp.int32, start.device)
    start.launch(overflow_kernel, 1, inputs=[start.offsets, n, capacity], outputs=[overflow], device=start.device)
    num_tiles = start.tiles_x * start.tiles_y
    # The sentinel, the tile count, sorts after every tile id: one more bit where it needs one.
    return _emit_sorted(start, capacity, num_tiles, max(int(num_tiles).bit_length(), 1)), overflow


def bin_gaussians(
    means2d: wp.array,
    radii: wp.array,
    depths: wp.array,
    width: int,
    height: int,
    allocate: Callable | None = None,
    zeros: Callable | None = None,
    read_count: Callable | None = None,
    *,
    conics: wp.array | None = None,
    opacities: wp.array | None = None,
    launch: Callable | None = None,
) -> TileBins:
    """Bin projected Gaussians into TILE_SIZE x TILE_SIZE tiles and sort each tile's list by depth.

    Args:
        means2d: [N] vec2 pixel means; radii: [N] vec2i per-axis pixel radii (0 = culled);
            depths: [N] float32 camera-space depths (> 0 for visible Gaussians).
        width, height: image size in pixels.
        conics, opacities: [N] vec3 and float32, as the blend reads them: given both, each
            Gaussian goes only into the tiles where it reaches alpha 1/255 at a pixel centre
            (the same image, fewer pairs); without them, into every tile of its rectangle.
        allocate, zeros: optional ``(shape, dtype, device) -> wp.array`` allocators (the torch face
            passes ones backed by torch's caching allocator); default ``wp.empty`` / ``wp.zeros``.
        read_count: optional ``(offsets) -> int`` reading the total intersection count, the last
            entry of ``offsets`` (an inclusive prefix sum of tile counts).
        launch: optional stand-in for ``wp.launch`` with its arguments (the torch face passes one
            that replays recorded launches); default ``wp.launch``.

    The one host synchronisation of a render happens here: the intersection count must be known
    on the host to size the sort buffers. :func:`start_binning` and :func:`finish_binning` are
    the two halves around it.
    """
    start = start_binning(
        means2d, radii, depths, width, height, allocate, zeros, conics=conics, opacities=opacities, launch=launch
    )
    n = start.offsets.shape[0]
    if read_count is None:
        total = int(start.offsets[n - 1 : n].numpy()[0])  # host sync: sizes the sort buffers
    else:
        total = int(read_count(start.offsets))
    return finish_binning(start, total)
