"""Exact k-nearest neighbours of every point among the others, on a sort-based multi-level grid.

Pure Warp. The points are sorted once by their 63-bit Morton code (21 bits per axis over the
bounding cube). Every cell of every level of the implicit octree is then a contiguous run of the
sorted array, so the same sort serves as a uniform grid at any cell size:

1. A first pass bounds each point's k-th neighbour distance R by the k best among its 2W
   neighbours in Morton order (real points, so R is an upper bound).
2. The search then visits, at the finest level whose cells are at least R wide, the few cells
   that overlap the ball of radius R, and scans their points. A cell holding more than
   LEAF_SIZE points is split into its 8 children instead of being scanned, and every cell whose
   box is farther than the current k-th best distance is skipped, so dense clusters next to
   sparse points, duplicated points and loose first-pass bounds all stay cheap.

Because the cells cover the whole ball of radius R and R bounds the k-th distance, the result is
exact for any distribution. Ties are broken by the smaller point index.
"""

from collections.abc import Callable

import numpy as np
import warp as wp

__all__ = ["MAX_K", "knn_search"]

MAX_K = 16
MORTON_BITS = wp.constant(21)
MORTON_MAX = wp.constant((1 << 21) - 1)
# A cell with more points than this is split into its children rather than scanned.
LEAF_SIZE = wp.constant(64)
# Neighbours on each side in Morton order that bound the k-th distance in the first pass.
WINDOW = wp.constant(8)
# Cells waiting to be visited; a cell that would overflow it is scanned instead of split (still
# exact, only slower). Kept small because Warp zero-fills local vectors per thread.
STACK_SIZE = 48
FLOAT_MAX = wp.constant(3.0e38)

topk_dist = wp.types.vector(length=MAX_K, dtype=wp.float32)
topk_index = wp.types.vector(length=MAX_K, dtype=wp.int32)
stack_int = wp.types.vector(length=STACK_SIZE, dtype=wp.int32)
stack_int64 = wp.types.vector(length=STACK_SIZE, dtype=wp.int64)


@wp.func
def pack_cell(cx: int, cy: int, cz: int):
    return wp.int64(cx) | (wp.int64(cy) << wp.int64(21)) | (wp.int64(cz) << wp.int64(42))


@wp.func
def unpack_cell(cell: wp.int64):
    mask = wp.int64(0x1FFFFF)
    return wp.vec3i(int(cell & mask), int((cell >> wp.int64(21)) & mask), int((cell >> wp.int64(42)) & mask))


@wp.kernel(enable_backward=False)
def bounds_kernel(
    points: wp.array(dtype=wp.vec3),
    chunk: int,
    bounds_out: wp.array(dtype=float),
    nonfinite_out: wp.array(dtype=wp.int32),
):
    """Bounding box (min xyz, max xyz in bounds_out[0:6]) and count of non-finite points, per chunk."""
    t = wp.tid()
    n = points.shape[0]
    lo = wp.vec3(FLOAT_MAX, FLOAT_MAX, FLOAT_MAX)
    hi = wp.vec3(-FLOAT_MAX, -FLOAT_MAX, -FLOAT_MAX)
    bad = int(0)
    for i in range(t * chunk, wp.min((t + 1) * chunk, n)):
        p = points[i]
        if wp.isfinite(p):
            lo = wp.min(lo, p)
            hi = wp.max(hi, p)
        else:
            bad += 1
    for a in range(3):
        wp.atomic_min(bounds_out, a, lo[a])
        wp.atomic_max(bounds_out, a + 3, hi[a])
    if bad > 0:
        wp.atomic_add(nonfinite_out, 0, bad)


@wp.func
def grid_scale(bounds: wp.array(dtype=float)):
    """Fine-grid cells per unit length: the bounding cube's longest side spans 2^21 cells."""
    side = wp.max(wp.max(bounds[3] - bounds[0], bounds[4] - bounds[1]), bounds[5] - bounds[2])
    return float(MORTON_MAX) / wp.max(side, 1.0e-30)


@wp.func
def fine_coord(x: float, origin: float, scale: float):
    """Fine-grid integer coordinate of x along one axis (the same expression for points and queries)."""
    return wp.clamp(int(wp.clamp((x - origin) * scale, -1.0, float(MORTON_MAX))), 0, MORTON_MAX)


@wp.func
def spread_bits(v: int):
    """Insert two zero bits between each of the low 21 bits of v."""
    x = wp.int64(v) & wp.int64(0x1FFFFF)
    x = (x | (x << wp.int64(32))) & wp.int64(0x1F00000000FFFF)
    x = (x | (x << wp.int64(16))) & wp.int64(0x1F0000FF0000FF)
    x = (x | (x << wp.int64(8))) & wp.int64(0x100F00F00F00F00F)
    x = (x | (x << wp.int64(4))) & wp.int64(0x10C30C30C30C30C3)
    x = (x | (x << wp.int64(2))) & wp.int64(0x1249249249249249)
    return x


@wp.func
def morton(cx: int, cy: int, cz: int):
    return spread_bits(cx) | (spread_bits(cy) << wp.int64(1)) | (spread_bits(cz) << wp.int64(2))


@wp.kernel(enable_backward=False)
def morton_kernel(
    points: wp.array(dtype=wp.vec3),
    bounds: wp.array(dtype=float),
    codes_out: wp.array(dtype=wp.int64),
    ids_out: wp.array(dtype=wp.int32),
):
    """Morton code of each point's fine-grid cell, and its index (the sort payload)."""
    i = wp.tid()
    p = points[i]
    scale = grid_scale(bounds)
    codes_out[i] = morton(
        fine_coord(p[0], bounds[0], scale), fine_coord(p[1], bounds[1], scale), fine_coord(p[2], bounds[2], scale)
    )
    ids_out[i] = i


@wp.kernel(enable_backward=False)
def gather_kernel(
    points: wp.array(dtype=wp.vec3), ids: wp.array(dtype=wp.int32), sorted_points_out: wp.array(dtype=wp.vec3)
):
    """Points in Morton order, so that neighbours in space are neighbours in memory."""
    i = wp.tid()
    sorted_points_out[i] = points[ids[i]]


@wp.func
def before(code: wp.int64, key: wp.int64, inclusive: int):
    """code < key, or code <= key when inclusive."""
    if inclusive != 0:
        return code <= key
    return code < key


@wp.func
def search_from(codes: wp.array(dtype=wp.int64), lo: int, hi: int, key: wp.int64, inclusive: int, hint: int):
    """First position in the sorted codes[lo:hi] not ``before`` key, galloping out from ``hint``.

    Cells near the query sit near it in Morton order, so this costs about 2 log2 of the distance
    instead of log2 of the whole range.
    """
    a = lo
    b = hi
    if b > a:
        h = wp.clamp(hint, a, b - 1)
        step = int(1)
        if before(codes[h], key, inclusive):
            a = h + 1
            while a + step - 1 < b and before(codes[a + step - 1], key, inclusive):
                a = a + step
                step = step * 2
            b = wp.min(a + step - 1, b)
        else:
            b = h
            while b - step >= a and not before(codes[b - step], key, inclusive):
                b = b - step
                step = step * 2
            a = wp.max(b - step + 1, a)
    while a < b:
        mid = (a + b) // 2
        if before(codes[mid], key, inclusive):
            a = mid + 1
        else:
            b = mid
    return a


@wp.func
def axis_gap(q: float, cell: int, cells: int, size: float, origin: float, slack: float):
    """Distance from q to the cell's extent along one axis, less ``slack`` (edge cells extend to
    infinity). The slack, one fine cell, absorbs the rounding of the cell bounds, so a cell that
    holds a point at the bound distance (0 for duplicates) is never skipped."""
    lo = origin + float(cell) * size
    hi = lo + size
    gap = float(0.0)
    if q < lo and cell > 0:
        gap = lo - q
    if q > hi and cell < cells - 1:
        gap = q - hi
    return wp.max(gap - slack, 0.0)


@wp.kernel(enable_backward=False)
def search_kernel(
    sorted_points: wp.array(dtype=wp.vec3),
    sorted_codes: wp.array(dtype=wp.int64),
    sorted_ids: wp.array(dtype=wp.int32),
    bounds: wp.array(dtype=float),
    k: int,
    sqdist_out: wp.array2d(dtype=float),
    index_out: wp.array2d(dtype=wp.int32),
):
    """The k nearest other points of the point at sorted position p, ascending by (distance, index)."""
    p = wp.tid()
    n = sorted_points.shape[0]
    q = sorted_points[p]
    best_d = topk_dist()
    best_i = topk_index()
    for j in range(k):
        best_d[j] = FLOAT_MAX
        best_i[j] = 2147483647

    # Pass 1: an upper bound of the k-th distance from neighbours in Morton order.
    w0 = wp.clamp(p - WINDOW, 0, wp.max(n - 2 * WINDOW - 1, 0))
    w1 = wp.min(w0 + 2 * WINDOW + 1, n)
    for m in range(w0, w1):
        if m != p:
            d2 = wp.length_sq(sorted_points[m] - q)
            if d2 <= best_d[k - 1]:
                gid = sorted_ids[m]
                if d2 < best_d[k - 1] or gid < best_i[k - 1]:
                    # Insertion into the sorted top-k, inline: a wp.func returning the two
                    # 16-wide lists by value made the whole search twice as slow on the CPU.
                    j = k - 1
                    while j > 0 and (d2 < best_d[j - 1] or (d2 == best_d[j - 1] and gid < best_i[j - 1])):
                        best_d[j] = best_d[j - 1]
                        best_i[j] = best_i[j - 1]
                        j -= 1
                    best_d[j] = d2
                    best_i[j] = gid
    # A little slack so that rounding never drops a point at exactly the bound.
    radius = wp.sqrt(best_d[k - 1]) * 1.0001 + 1.0e-30
    bound2 = radius * radius

    # Pass 2: exact search from the finest level whose cells are at least `radius` wide.
    scale = grid_scale(bounds)
    level = int(MORTON_BITS)
    if 2.0 * radius * scale >= 1.0:
        level = wp.clamp(int(MORTON_BITS) - int(wp.ceil(wp.log2(2.0 * radius * scale))), 0, int(MORTON_BITS))
    shift = int(MORTON_BITS) - level
    c0x = fine_coord(q[0] - radius, bounds[0], scale) >> shift
    c1x = fine_coord(q[0] + radius, bounds[0], scale) >> shift
    c0y = fine_coord(q[1] - radius, bounds[1], scale) >> shift
    c1y = fine_coord(q[1] + radius, bounds[1], scale) >> shift
    c0z = fine_coord(q[2] - radius, bounds[2], scale) >> shift
    c1z = fine_coord(q[2] + radius, bounds[2], scale) >> shift

    for j in range(k):
        best_d[j] = FLOAT_MAX
        best_i[j] = 2147483647
    stack_cell = stack_int64()
    stack_level = stack_int()
    stack_lo = stack_int()
    stack_hi = stack_int()
    # The query's own cell goes on the stack last, so that it is visited first: the neighbours it
    # holds tighten the k-th distance early and let the other cells be skipped by their boxes.
    own = pack_cell(
        fine_coord(q[0], bounds[0], scale) >> shift,
        fine_coord(q[1], bounds[1], scale) >> shift,
        fine_coord(q[2], bounds[2], scale) >> shift,
    )
    top = int(0)
    for cz in range(c0z, c1z + 1):
        for cy in range(c0y, c1y + 1):
            for cx in range(c0x, c1x + 1):
                packed = pack_cell(cx, cy, cz)
                if packed != own:
                    stack_cell[top] = packed
                    stack_level[top] = level
                    stack_lo[top] = 0
                    stack_hi[top] = n
                    top += 1
    stack_cell[top] = own
    stack_level[top] = level
    stack_lo[top] = 0
    stack_hi[top] = n
    top += 1

    while top > 0:
        top -= 1
        cell = unpack_cell(stack_cell[top])
        cx = cell[0]
        cy = cell[1]
        cz = cell[2]
        cl = stack_level[top]
        cells = 1 << cl
        size = float(1 << (int(MORTON_BITS) - cl)) / scale
        gx = axis_gap(q[0], cx, cells, size, bounds[0], 1.0 / scale)
        gy = axis_gap(q[1], cy, cells, size, bounds[1], 1.0 / scale)
        gz = axis_gap(q[2], cz, cells, size, bounds[2], 1.0 / scale)
        limit = wp.min(bound2, best_d[k - 1]) * 1.0002
        if gx * gx + gy * gy + gz * gz > limit:
            continue
        cell_shift = wp.int64(3 * (int(MORTON_BITS) - cl))
        prefix = morton(cx, cy, cz)
        first = prefix << cell_shift
        # The cell's last fine code; (prefix + 1) << shift would overflow for the far corner cell.
        last = first | ((wp.int64(1) << cell_shift) - wp.int64(1))
        start = search_from(sorted_codes, stack_lo[top], stack_hi[top], first, 0, p)
        end = search_from(sorted_codes, start, stack_hi[top], last, 1, start)
        if end - start > LEAF_SIZE and cl < int(MORTON_BITS) and top + 8 <= STACK_SIZE:
            # The child holding the query is pushed last, so visited first.
            child_shift = int(MORTON_BITS) - cl - 1
            own_child = (
                ((fine_coord(q[0], bounds[0], scale) >> child_shift) & 1)
                | (((fine_coord(q[1], bounds[1], scale) >> child_shift) & 1) << 1)
                | (((fine_coord(q[2], bounds[2], scale) >> child_shift) & 1) << 2)
            )
            for order in range(8):
                child = order ^ 7 ^ own_child
                stack_cell[top] = pack_cell(
                    2 * cx + (child & 1), 2 * cy + ((child >> 1) & 1), 2 * cz + ((child >> 2) & 1)
                )
                stack_level[top] = cl + 1
                stack_lo[top] = start
                stack_hi[top] = end
                top += 1
            continue
        for m in range(start, end):
            if m != p:
                d2 = wp.length_sq(sorted_points[m] - q)
                if d2 <= best_d[k - 1]:
                    gid = sorted_ids[m]
                    if d2 < best_d[k - 1] or gid < best_i[k - 1]:
                        # Insertion into the sorted top-k, inline: a wp.func returning the two
                        # 16-wide lists by value made the whole search twice as slow on the CPU.
                        j = k - 1
                        while j > 0 and (d2 < best_d[j - 1] or (d2 == best_d[j - 1] and gid < best_i[j - 1])):
                            best_d[j] = best_d[j - 1]
                            best_i[j] = best_i[j - 1]
                            j -= 1
                        best_d[j] = d2
                        best_i[j] = gid

    i = sorted_ids[p]
    for j in range(k):
        sqdist_out[i, j] = best_d[j]
        index_out[i, j] = best_i[j]


def knn_search(
    points: wp.array,
    k: int = 3,
    sqdist_out: wp.array | None = None,
    index_out: wp.array | None = None,
    allocate: Callable | None = None,
):
    """Exact k nearest other points of every point.

    Args:
        points: [N] vec3 (float32) Warp array, any device.
        k: neighbours per point, 1..16, less than N.
        sqdist_out, index_out: optional [N, k] float32 / int32 outputs (allocated when None).
        allocate: optional ``(shape, dtype, device) -> wp.array`` for the scratch buffers (the
            torch face passes one backed by torch's caching allocator); default ``wp.empty``.

    Returns:
        (sqdist [N, k] float32, index [N, k] int32), ascending by distance, ties by index.

    Raises:
        ValueError: empty input, k out of range or not below N, NaN or infinite coordinates.
        Checking the coordinates reads one integer back to the host.
    """
    if points.dtype != wp.vec3 or points.ndim != 1:
        raise ValueError(f"points must be a 1-D Warp array of vec3, got dtype {points.dtype} with {points.ndim} dims")
    n = points.shape[0]
    if n == 0:
        raise ValueError("points is empty: there are no neighbours to find")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= MAX_K:
        raise ValueError(f"k must be an int in 1..{MAX_K}, got {k!r}")
    if k >= n:
        raise ValueError(f"k={k} needs at least k+1 points, got {n}")
    device = points.device
    chunk = 256
    bounds = wp.array([3.0e38] * 3 + [-3.0e38] * 3, dtype=float, device=device)
    nonfinite = wp.zeros(1, dtype=wp.int32, device=device)
    wp.launch(
        bounds_kernel, (n + chunk - 1) // chunk, inputs=[points, chunk], outputs=[bounds, nonfinite], device=device
    )
    bad = int(nonfinite.numpy()[0])
    if bad:
        raise ValueError(f"points has {bad} point(s) with NaN or infinite coordinates")
    if allocate is None:
        allocate = lambda shape, dtype, dev: wp.empty(shape, dtype=dtype, device=dev)
    codes = allocate((2 * n,), wp.int64, device)  # radix_sort_pairs needs twice the count
    ids = allocate((2 * n,), wp.int32, device)
    wp.launch(morton_kernel, n, inputs=[points, bounds], outputs=[codes, ids], device=device)
    wp.utils.radix_sort_pairs(codes, ids, n, end_bit=63)
    sorted_points = allocate((n,), wp.vec3, device)
    wp.launch(gather_kernel, n, inputs=[points, ids], outputs=[sorted_points], device=device)
    if sqdist_out is None:
        sqdist_out = wp.empty((n, k), dtype=float, device=device)
    if index_out is None:
        index_out = wp.empty((n, k), dtype=wp.int32, device=device)
    wp.launch(
        search_kernel,
        n,
        inputs=[sorted_points, codes, ids, bounds, int(k)],
        outputs=[sqdist_out, index_out],
        device=device,
    )
    return sqdist_out, index_out
