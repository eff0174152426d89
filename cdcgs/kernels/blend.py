"""Front-to-back alpha compositing of depth-sorted Gaussians per tile, and its adjoint.

Pure Warp. One thread per pixel, one TILE_SIZE x TILE_SIZE tile (BLOCK_SIZE = 256 threads) per
block: launch with ``dim=tiles_x * tiles_y * BLOCK_SIZE`` and ``block_dim=BLOCK_SIZE``. The tiles'
lists come from ``binning.bin_gaussians``: ``sorted_gauss_ids`` and ``tile_ranges``, a
[tiles_y * tiles_x, 2] int32 array of [start, end) per tile (row-major tile numbers).

Both passes walk the tile's list in batches of BLOCK_SIZE Gaussians; on CUDA the block loads each
batch into shared memory together (``_lanes.tile_batch``), on the CPU each pixel reads global
memory. The backward pass is written by hand: it walks each pixel's list back to front from the
last contributor the forward pass stored, recovering transmittance by division, sums each
Gaussian's gradients over the warp in registers and lets one lane add them with atomics.
"""

import warp as wp

from ._constants import BLOCK_SIZE, TILE_SIZE
from ._lanes import (
    BATCH_FIELDS,
    BATCH_LOAD,
    BATCH_MAX,
    BATCH_STORE,
    GRADIENTS_ADD,
    GRADIENTS_READ,
    GRADIENTS_ZERO,
    atomic_max_nonnegative,
    batch_max,
    block_count,
    block_gradients,
    block_max_int,
    block_sync,
    lane_any,
    lane_leads,
    lane_max,
    lane_max_int,
    lane_sum,
    lane_sum_vec2,
    lane_sum_vec3,
    on_cuda,
    tile_batch,
    tile_ids,
)
from .binning import footprint_bound
from .projection import ALPHA_THRESHOLD

__all__ = [
    "MAX_EXACT",
    "MAX_RACY_KEEP",
    "MAX_RACY_RANK",
    "VIEW_TABLE_COLUMNS",
    "VIEW_TABLE_MAP",
    "W_MAX_ALPHA",
    "W_MAX_WEIGHT",
    "blend_backward_kernel",
    "blend_backward_lean_kernel",
    "blend_backward_lean_warp_kernel",
    "blend_backward_warp_kernel",
    "blend_forward_chunked_kernel",
    "blend_forward_kernel",
    "complexity_kernel",
    "complexity_views_kernel",
    "walk_chunks_kernel",
]

# CUDA: --use_fast_math (approximate exp and division, as gsplat builds its kernels; the CPU build
# ignores it), and no grid-stride loop (one pixel per thread, fewer registers).
wp.set_module_options({"fast_math": True, "default_grid_stride": False})

# Alpha is clamped here so that one Gaussian never makes a pixel fully opaque (3DGS).
MAX_ALPHA = wp.constant(0.99)
# Compositing stops before a Gaussian that would bring transmittance below this (3DGS).
MIN_TRANSMITTANCE = wp.constant(1.0e-4)


@wp.func
def tile_pixel_of(tile: int, local: int, tiles_x: int):
    """Pixel (x, y) of thread ``local`` of the block that takes ``tile``, and the tile."""
    tile_y = tile // tiles_x
    tile_x = tile - tile_y * tiles_x
    return wp.vec3i(tile_x * TILE_SIZE + local % TILE_SIZE, tile_y * TILE_SIZE + local // TILE_SIZE, tile)


@wp.func
def tile_pixel(tid: int, tiles_x: int):
    """Pixel (x, y) and tile index of thread ``tid`` when each tile is a block of BLOCK_SIZE threads."""
    tile = tid // BLOCK_SIZE
    return tile_pixel_of(tile, tid - tile * BLOCK_SIZE, tiles_x)


@wp.func
def chunk_tile(chunk: int, chunk_ends: wp.array(dtype=wp.int32)):
    """The tile whose chunks hold ``chunk``: the first t with ``chunk_ends[t]`` > ``chunk``."""
    lo = int(0)
    hi = chunk_ends.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if chunk_ends[mid] > chunk:
            hi = mid
        else:
            lo = mid + 1
    return lo


@wp.func
def splat_alpha(mean: wp.vec2, conic: wp.vec3, opacity: float, px: float, py: float):
    """alpha = min(0.99, opacity exp(-d^T conic d / 2)) at (px, py); 0 where the Gaussian does not
    composite (power > 0, or alpha below 1/255)."""
    dx = mean[0] - px
    dy = mean[1] - py
    power = -0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy
    if power > 0.0:
        return 0.0
    alpha = wp.min(MAX_ALPHA, opacity * wp.exp(power))
    if alpha < ALPHA_THRESHOLD:
        return 0.0
    return alpha


@wp.func
def shape_field(
    field: int,
    g: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
):
    """Field 0 (mean x, mean y, conic a, conic b) or 1 (conic c, opacity, 0, 0) of Gaussian ``g``:
    what decides whether it composites at a pixel."""
    if field == 0:
        m = means2d[g]
        q = conics[g]
        return wp.vec4(m[0], m[1], q[0], q[1])
    return wp.vec4(conics[g][2], opacities[g], 0.0, 0.0)


@wp.func
def gaussian_field(
    field: int,
    g: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    depths: wp.array(dtype=float),
):
    """Gaussian ``g`` packed as the blend passes read it: fields 0 and 1 (``shape_field``), 2 (colour
    r, g, b, depth), read only where it composites."""
    if field < 2:
        return shape_field(field, g, means2d, conics, opacities)
    c = colors[g]
    return wp.vec4(c[0], c[1], c[2], depths[g])


@wp.func
def batch_field(
    staged: int,
    field: int,
    slot: int,
    g: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    depths: wp.array(dtype=float),
):
    """``gaussian_field`` of the Gaussian in ``slot`` of the staged batch (CUDA), or of Gaussian ``g``
    read from global memory (CPU)."""
    if staged != 0:
        return tile_batch(BATCH_LOAD, field * BLOCK_SIZE + slot, wp.vec4())
    return gaussian_field(field, g, means2d, conics, colors, opacities, depths)


@wp.func
def stage_gaussian(
    slot: int,
    g: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    depths: wp.array(dtype=float),
):
    """Copy Gaussian ``g`` into ``slot`` of the block's shared batch (CUDA)."""
    tile_ids(BATCH_STORE, slot, g)
    for field in range(BATCH_FIELDS):
        tile_batch(
            BATCH_STORE, field * BLOCK_SIZE + slot, gaussian_field(field, g, means2d, conics, colors, opacities, depths)
        )


@wp.func
def shape_alpha(shape: wp.vec4, extra: wp.vec4, px: float, py: float):
    """``splat_alpha`` of a Gaussian given as fields 0 and 1."""
    return splat_alpha(wp.vec2(shape[0], shape[1]), wp.vec3(shape[2], shape[3], extra[0]), extra[1], px, py)


def _blend_forward(chunked: bool):
    """The blend's forward kernel; with ``chunked`` it also saves the checkpoints of the chunked
    adjoint (which take registers: 56 a thread against 48 on an H100, four blocks an SM instead
    of five), so that the forward of a render without them is the lean one."""

    @wp.kernel(enable_backward=False)
    def blend_forward_kernel(
        tile_ranges: wp.array2d(dtype=wp.int32),
        sorted_gauss_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        colors: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        depths: wp.array(dtype=float),
        background: wp.array(dtype=wp.vec3),
        width: int,
        height: int,
        tiles_x: int,
        chunk_size: int,
        image_out: wp.array2d(dtype=wp.vec3),
        transmittance_out: wp.array2d(dtype=float),
        depth_out: wp.array2d(dtype=float),
        last_contributor_out: wp.array2d(dtype=wp.int32),
        checkpoint_color_out: wp.array2d(dtype=wp.vec4),
        checkpoint_depth_out: wp.array2d(dtype=float),
        tile_last_out: wp.array(dtype=wp.int32),
    ):
        """Colour (over ``background[0]``), final transmittance, weighted depth sum and last contributor per pixel.

        The tile's list is walked in batches of BLOCK_SIZE. On CUDA the block's threads (one tile) first
        load the batch into shared memory together, one Gaussian per thread, and every pixel then reads
        it from there; a pixel that turns opaque leaves the batch early and waits at the barrier, and
        the block stops when all its pixels are opaque. On the CPU each pixel reads global memory.

        For the chunked adjoint (``chunk_size`` > 0, a multiple of BLOCK_SIZE; 0: none of this, and the
        last three outputs may be None): at each list position p = start + c * chunk_size (c >= 1) that
        a pixel reaches still compositing, its colour so far and transmittance (r, g, b, T) go to
        ``checkpoint_color_out[p // chunk_size + tile, local]`` and its depth sum to
        ``checkpoint_depth_out`` alike (rows: pairs // chunk_size + tiles; the row is unique to the
        tile and boundary); ``tile_last_out[tile]`` (-1 before) becomes the largest last contributor
        of the tile's pixels.
        """
        tid = wp.tid()
        pix = tile_pixel(tid, tiles_x)
        local = tid % BLOCK_SIZE
        x = pix[0]
        y = pix[1]
        px = float(x) + 0.5
        py = float(y) + 0.5
        start = tile_ranges[pix[2], 0]
        end = tile_ranges[pix[2], 1]
        staged = on_cuda()
        done = int(0)
        if x >= width or y >= height:
            done = 1  # pixels outside the image only help load batches

        transmittance = float(1.0)
        color = wp.vec3(0.0, 0.0, 0.0)
        depth = float(0.0)
        last = start - 1
        batch = start
        while batch < end:
            count = wp.min(BLOCK_SIZE, end - batch)
            if staged != 0:
                if block_count(done) >= BLOCK_SIZE:
                    break
                if local < count:
                    stage_gaussian(local, sorted_gauss_ids[batch + local], means2d, conics, colors, opacities, depths)
                block_sync()
            if wp.static(chunked) and chunk_size > 0 and done == 0 and batch > start:
                if (batch - start) % chunk_size == 0:  # a chunk boundary, reached still compositing
                    row = batch // chunk_size + pix[2]
                    checkpoint_color_out[row, local] = wp.vec4(color[0], color[1], color[2], transmittance)
                    checkpoint_depth_out[row, local] = depth
            if done == 0:
                for j in range(count):
                    g = int(0)
                    if staged == 0:
                        g = sorted_gauss_ids[batch + j]
                    shape = batch_field(staged, 0, j, g, means2d, conics, colors, opacities, depths)
                    extra = batch_field(staged, 1, j, g, means2d, conics, colors, opacities, depths)
                    alpha = shape_alpha(shape, extra, px, py)
                    if alpha > 0.0:
                        next_transmittance = transmittance * (1.0 - alpha)
                        if next_transmittance < MIN_TRANSMITTANCE:
                            done = 1
                            break
                        look = batch_field(staged, 2, j, g, means2d, conics, colors, opacities, depths)
                        weight = alpha * transmittance
                        color += weight * wp.vec3(look[0], look[1], look[2])
                        depth += weight * look[3]
                        transmittance = next_transmittance
                        last = batch + j
            if staged != 0:
                block_sync()  # the batch is read before the next one overwrites it
            elif done != 0:
                break
            batch += BLOCK_SIZE

        if x < width and y < height:
            image_out[y, x] = color + transmittance * background[0]
            transmittance_out[y, x] = transmittance
            depth_out[y, x] = depth
            last_contributor_out[y, x] = last
        if wp.static(chunked):
            tile_last = block_max_int(last)  # the block's (CUDA); the pixel's own on the CPU
            if staged == 0 or local == 0:
                wp.atomic_max(tile_last_out, pix[2], tile_last)

    return blend_forward_kernel


# Without checkpoints (``chunk_size`` must be 0; the last three outputs may be None), and with
# them (``chunk_size`` > 0): ``rasterize`` launches the second for a chunked adjoint.
blend_forward_kernel = _blend_forward(False)
blend_forward_chunked_kernel = _blend_forward(True)


@wp.kernel(enable_backward=False)
def walk_chunks_kernel(
    tile_ranges: wp.array2d(dtype=wp.int32),
    tile_last: wp.array(dtype=wp.int32),
    chunk_size: int,
    chunks_out: wp.array(dtype=wp.int32),
):
    """Chunks of ``chunk_size`` list entries that the adjoint walks in each tile: its list from the
    start up to the largest last contributor of its pixels (``tile_last``, from the forward pass),
    0 when no pixel composites anything. Their inclusive prefix sum is the adjoint's
    ``chunk_ends``."""
    t = wp.tid()
    walk = tile_last[t] - tile_ranges[t, 0] + 1
    chunks_out[t] = wp.max((walk + chunk_size - 1) // chunk_size, 0)


def _blend_backward(sums: bool, block: bool):
    """The blend adjoint; with ``sums`` False it leaves out the depth gradients and the AbsGS sums
    (for a loss that does not use the depth and a strategy that does not read the sums: a sixth of
    its time on an H100 goes to their warp sums and atomics). With ``block`` True (CUDA; the CPU
    code is the same either way) the warps add each Gaussian's sums into the block's shared memory
    (``_lanes.block_gradients``) and one thread per Gaussian adds the tile's sum to global memory
    after the batch; with False each warp adds its own sums to global memory."""

    # 4 blocks of BLOCK_SIZE (256) per SM: at most 64 registers (what the kernel without sums
    # needs; 48 spill).
    @wp.kernel(enable_backward=False, launch_bounds=(BLOCK_SIZE, 4))
    def blend_backward_kernel(
        tile_ranges: wp.array2d(dtype=wp.int32),
        sorted_gauss_ids: wp.array(dtype=wp.int32),
        means2d: wp.array(dtype=wp.vec2),
        conics: wp.array(dtype=wp.vec3),
        colors: wp.array(dtype=wp.vec3),
        opacities: wp.array(dtype=float),
        depths: wp.array(dtype=float),
        background: wp.array(dtype=wp.vec3),
        width: int,
        height: int,
        tiles_x: int,
        chunk_size: int,
        chunk_ends: wp.array(dtype=wp.int32),
        transmittance: wp.array2d(dtype=float),
        last_contributor: wp.array2d(dtype=wp.int32),
        image: wp.array2d(dtype=wp.vec3),
        depth_sum: wp.array2d(dtype=float),
        checkpoint_color: wp.array2d(dtype=wp.vec4),
        checkpoint_depth: wp.array2d(dtype=float),
        grad_image: wp.array2d(dtype=wp.vec3),
        grad_alpha: wp.array2d(dtype=float),
        grad_depth: wp.array2d(dtype=float),
        grad_means2d_out: wp.array(dtype=wp.vec2),
        grad_conics_out: wp.array(dtype=wp.vec3),
        grad_colors_out: wp.array(dtype=wp.vec3),
        grad_opacities_out: wp.array(dtype=float),
        grad_depths_out: wp.array(dtype=float),
        absgrad_means2d_out: wp.array(dtype=wp.vec2),
    ):
        """Adjoint of ``blend_forward_kernel`` for image, alpha (= 1 - transmittance) and depth sum.

        Also accumulates, per Gaussian, the sum over pixels of the absolute per-pixel gradient of its
        2D mean (AbsGS). ``grad_alpha`` may be None (a loss that does not use alpha).

        Each pixel walks its list back to front from its last contributor, recovering the transmittance
        T_i in front of Gaussian i by division and keeping S, the colour (and depth) composited behind
        it: S = sum over j > i of c_j alpha_j T_j. With C = sum c_i alpha_i T_i + T_final background,
        dC/dalpha_i = c_i T_i - (S + T_final background) / (1 - alpha_i).

        The 32 lanes of a warp (two rows of one tile) walk the tile's list together, from the last
        contributor of any of them down to the tile's start; a lane whose pixel the Gaussian does not
        touch adds zeros. Each Gaussian's gradients are summed over the warp in registers and one lane
        adds them to global memory (``_lanes``), so no lane may leave the loop early.

        Chunked (``chunk_ends`` not empty): block b walks chunk b of the table instead of a whole
        tile. ``chunk_ends`` [tiles] is the inclusive prefix sum of the tiles' chunks, the pieces
        [start + c * chunk_size, start + (c + 1) * chunk_size) of the list up to the tile's last
        contributor (``walk_chunks_kernel``); blocks past the last chunk leave at once. A pixel that
        composites past its chunk starts the walk from the forward pass's checkpoint at the chunk's
        end: T there, and S = (image - T_final background) - the colour composited before it (and
        the depth sum alike). ``image``, ``depth_sum`` and the checkpoints are the forward pass's
        (None, with ``chunk_ends`` empty: one block per tile, walking all of it).
        """
        tid = wp.tid()
        local = tid % BLOCK_SIZE
        chunk = tid // BLOCK_SIZE
        tile = chunk
        chunked = chunk_ends.shape[0]
        if chunked > 0:
            if chunk >= chunk_ends[chunked - 1]:
                return  # past the last chunk: the whole block leaves before any barrier
            tile = chunk_tile(chunk, chunk_ends)
        pix = tile_pixel_of(tile, local, tiles_x)
        x = pix[0]
        y = pix[1]
        px = float(x) + 0.5
        py = float(y) + 0.5
        start = tile_ranges[tile, 0]
        first = start  # this block walks [first, stop) of the tile's list
        stop = tile_ranges[tile, 1]
        if chunked > 0:
            before = int(0)
            if tile > 0:
                before = chunk_ends[tile - 1]
            first = start + (chunk - before) * chunk_size
            stop = wp.min(first + chunk_size, stop)

        final_transmittance = float(1.0)
        g_color = wp.vec3(0.0, 0.0, 0.0)
        g_depth = float(0.0)
        g_alpha = float(0.0)
        last = start - 1  # pixels outside the image take part in the warp's collectives with nothing to add
        if x < width and y < height:
            final_transmittance = transmittance[y, x]
            g_color = grad_image[y, x]
            if wp.static(sums):
                g_depth = grad_depth[y, x]
            if grad_alpha.shape[0] > 0:  # None: the loss does not use alpha
                g_alpha = grad_alpha[y, x]
            last = last_contributor[y, x]
        t = final_transmittance
        # d(color)/d(alpha_i) and d(alpha_pixel)/d(alpha_i) both carry T_final / (1 - alpha_i).
        g_final = final_transmittance * (g_alpha - wp.dot(background[0], g_color))

        fields = int(9)  # of block_gradients: colour, opacity, mean, conic (and depth, AbsGS sums)
        if wp.static(sums):
            fields = 12
        zero4 = wp.vec4(0.0, 0.0, 0.0, 0.0)
        behind_color = wp.vec3(0.0, 0.0, 0.0)  # S: colour composited behind Gaussian i
        behind_depth = float(0.0)
        if last >= stop:  # the pixel composites past this chunk: start from the checkpoint at its end
            row = stop // chunk_size + tile
            checkpoint = checkpoint_color[row, local]
            t = checkpoint[3]
            composited = image[y, x] - final_transmittance * background[0]
            behind_color = composited - wp.vec3(checkpoint[0], checkpoint[1], checkpoint[2])
            if wp.static(sums):
                behind_depth = depth_sum[y, x] - checkpoint_depth[row, local]
            last = stop - 1
        if last < first:
            last = first - 1  # nothing of this chunk
        # The list is walked back to front in batches of BLOCK_SIZE from the last contributor of any
        # pixel of the block (on CUDA each batch is loaded into shared memory together, as in the forward pass);
        # within a batch a warp starts at the last contributor of any of its lanes, so all its lanes
        # visit the same Gaussians (the collectives need that) and none visits one behind them all. On
        # the CPU every thread is its own warp and block: it starts at its own last contributor.
        staged = on_cuda()
        warp_last = lane_max_int(last)
        batch = block_max_int(warp_last)  # index of the batch's first (back-most) Gaussian
        while batch >= first:
            count = wp.min(BLOCK_SIZE, batch - first + 1)
            if staged != 0:
                if local < count:
                    stage_gaussian(local, sorted_gauss_ids[batch - local], means2d, conics, colors, opacities, depths)
                    if wp.static(block):
                        block_gradients(GRADIENTS_ZERO, local, 0, fields, zero4, zero4, zero4)
                block_sync()
            for j in range(wp.max(batch - warp_last, 0), count):
                k = batch - j
                g = int(0)
                if staged == 0:
                    g = sorted_gauss_ids[k]
                shape = batch_field(staged, 0, j, g, means2d, conics, colors, opacities, depths)
                extra = batch_field(staged, 1, j, g, means2d, conics, colors, opacities, depths)
                dx = shape[0] - px
                dy = shape[1] - py
                power = -0.5 * (shape[2] * dx * dx + extra[0] * dy * dy) - shape[3] * dx * dy
                gauss = wp.exp(wp.min(power, 0.0))
                raw_alpha = extra[1] * gauss
                alpha = wp.min(MAX_ALPHA, raw_alpha)
                valid = int(0)
                if k <= last and power <= 0.0 and alpha >= ALPHA_THRESHOLD:
                    valid = 1
                if lane_any(valid) == 0:
                    continue
                d_color = wp.vec3(0.0, 0.0, 0.0)
                d_depth = float(0.0)
                d_opacity = float(0.0)
                d_mean = wp.vec2(0.0, 0.0)
                d_conic = wp.vec3(0.0, 0.0, 0.0)
                if valid != 0:
                    look = batch_field(staged, 2, j, g, means2d, conics, colors, opacities, depths)
                    c = wp.vec3(look[0], look[1], look[2])
                    front = 1.0 / (1.0 - alpha)
                    t = t * front
                    weight = alpha * t
                    d_color = weight * g_color
                    d_depth = weight * g_depth
                    grad_alpha_i = (
                        wp.dot(t * c - front * behind_color, g_color) + (t * look[3] - front * behind_depth) * g_depth
                    )
                    grad_alpha_i += front * g_final
                    behind_color += weight * c
                    behind_depth += weight * look[3]
                    if raw_alpha < MAX_ALPHA:
                        d_opacity = gauss * grad_alpha_i
                        grad_power = raw_alpha * grad_alpha_i
                        d_mean = grad_power * wp.vec2(
                            -(shape[2] * dx + shape[3] * dy), -(extra[0] * dy + shape[3] * dx)
                        )
                        d_conic = grad_power * wp.vec3(-0.5 * dx * dx, -dx * dy, -0.5 * dy * dy)
                d_abs = wp.vec2(wp.abs(d_mean[0]), wp.abs(d_mean[1]))
                if wp.static(block):
                    if staged != 0:
                        block_gradients(
                            GRADIENTS_ADD,
                            j,
                            0,
                            fields,
                            wp.vec4(d_color[0], d_color[1], d_color[2], d_opacity),
                            wp.vec4(d_mean[0], d_mean[1], d_conic[0], d_conic[1]),
                            wp.vec4(d_conic[2], d_depth, d_abs[0], d_abs[1]),
                        )
                        continue
                d_color = lane_sum_vec3(d_color)
                if wp.static(sums):
                    d_depth = lane_sum(d_depth)
                d_opacity = lane_sum(d_opacity)
                d_mean = lane_sum_vec2(d_mean)
                if wp.static(sums):
                    d_abs = lane_sum_vec2(d_abs)
                d_conic = lane_sum_vec3(d_conic)
                if lane_leads() != 0:
                    if staged != 0:
                        g = tile_ids(BATCH_LOAD, j, 0)
                    wp.atomic_add(grad_colors_out, g, d_color)
                    wp.atomic_add(grad_opacities_out, g, d_opacity)
                    wp.atomic_add(grad_means2d_out, g, d_mean)
                    wp.atomic_add(grad_conics_out, g, d_conic)
                    if wp.static(sums):
                        wp.atomic_add(grad_depths_out, g, d_depth)
                        wp.atomic_add(absgrad_means2d_out, g, d_abs)
            if staged != 0:
                block_sync()  # the batch is read before the next one overwrites it
                if wp.static(block):
                    # The tile's sums of the Gaussian in this thread's slot, to global memory.
                    if local < count:
                        head = block_gradients(GRADIENTS_READ, local, 0, fields, zero4, zero4, zero4)
                        middle = block_gradients(GRADIENTS_READ, local, 1, fields, zero4, zero4, zero4)
                        tail = block_gradients(GRADIENTS_READ, local, 2, fields, zero4, zero4, zero4)
                        if not (
                            head == zero4 and middle == zero4 and tail == zero4
                        ):  # else no pixel of the tile took it
                            g = tile_ids(BATCH_LOAD, local, 0)
                            wp.atomic_add(grad_colors_out, g, wp.vec3(head[0], head[1], head[2]))
                            wp.atomic_add(grad_opacities_out, g, head[3])
                            wp.atomic_add(grad_means2d_out, g, wp.vec2(middle[0], middle[1]))
                            wp.atomic_add(grad_conics_out, g, wp.vec3(middle[2], middle[3], tail[0]))
                            if wp.static(sums):
                                wp.atomic_add(grad_depths_out, g, tail[1])
                                wp.atomic_add(absgrad_means2d_out, g, wp.vec2(tail[2], tail[3]))
            batch -= BLOCK_SIZE

    return blend_backward_kernel


# On CUDA the warps' sums go through the block's shared memory (``block``), measured faster
# (docs/benchmarks.md); the ``_warp_`` kernels add each warp's sums to global memory, as before.
blend_backward_kernel = _blend_backward(True, True)
blend_backward_warp_kernel = _blend_backward(True, False)
# The same for a loss without the depth sum and no AbsGS sums: it reads no ``grad_depth`` and
# leaves ``grad_depths_out`` and ``absgrad_means2d_out`` untouched (None may be passed for all three).
blend_backward_lean_kernel = _blend_backward(False, True)
blend_backward_lean_warp_kernel = _blend_backward(False, False)


# How the complexity pass finds w_max(p): the largest alpha * T up to the pixel's last contributor
# (the formula), or the largest alpha over the pixel's whole tile list (the CDC-GS code, whose
# first pass never updates T).
W_MAX_WEIGHT = wp.constant(0)
W_MAX_ALPHA = wp.constant(1)
# The complexity pass's per-Gaussian max: exact (an atomic max over every pixel), or the CDC-GS
# code's racy store emulated in two launches: RACY_RANK gives each (tile, Gaussian) pair the key
# of one pseudo-randomly ranked contributing pixel, RACY_KEEP lets only that pixel's value in.
MAX_EXACT = wp.constant(0)
MAX_RACY_RANK = wp.constant(1)
MAX_RACY_KEEP = wp.constant(2)


@wp.func
def racy_key(seed: int, g: int, local: int):
    """A key unique within a tile for (Gaussian g, pixel ``local`` of the tile): 23 pseudo-random
    bits over the pixel's 8, so the largest key picks a random contributing pixel."""
    state = wp.rand_init(seed * BLOCK_SIZE + local, g)
    return (wp.randi(state) & 0x7FFFFF) * BLOCK_SIZE + local


@wp.func
def stage_shape(
    slot: int,
    g: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
):
    """Copy fields 0 and 1 of Gaussian ``g`` (all the complexity pass reads) into ``slot`` of the
    block's shared batch (CUDA)."""
    tile_ids(BATCH_STORE, slot, g)
    for field in range(2):
        tile_batch(BATCH_STORE, field * BLOCK_SIZE + slot, shape_field(field, g, means2d, conics, opacities))


@wp.func
def shape_of(
    staged: int,
    field: int,
    slot: int,
    g: int,
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
):
    """Field 0 or 1 (``gaussian_field``) of the Gaussian in ``slot`` of the staged batch (CUDA), or of
    Gaussian ``g`` read from global memory (CPU)."""
    if staged != 0:
        return tile_batch(BATCH_LOAD, field * BLOCK_SIZE + slot, wp.vec4())
    return shape_field(field, g, means2d, conics, opacities)


@wp.func
def support_box(mean: wp.vec2, conic: wp.vec3, opacity: float, width: int, height: int):
    """Pixels [x0, x1] x [y0, y1] (clamped to the image) holding every pixel where the Gaussian's
    alpha reaches 1/255: the box of its footprint ellipse (``footprint_bound``, whose margin covers
    rounding) a pixel wider on each side; the whole image where the conic is degenerate."""
    det = conic[0] * conic[2] - conic[1] * conic[1]
    if not (det > 0.0):
        return wp.vec4i(0, width - 1, 0, height - 1)
    bound = footprint_bound(opacity)
    reach_x = wp.sqrt(bound * conic[2] / det) + 1.0
    reach_y = wp.sqrt(bound * conic[0] / det) + 1.0
    # pixel x has its centre at x + 0.5
    x0 = wp.max(int(wp.floor(mean[0] - reach_x - 0.5)), 0)
    x1 = wp.min(int(wp.ceil(mean[0] + reach_x - 0.5)), width - 1)
    y0 = wp.max(int(wp.floor(mean[1] - reach_y - 0.5)), 0)
    y1 = wp.min(int(wp.ceil(mean[1] + reach_y - 0.5)), height - 1)
    return wp.vec4i(x0, x1, y0, y1)


@wp.kernel(enable_backward=False)
def w_max_alpha_kernel(
    tile_ranges: wp.array2d(dtype=wp.int32),
    sorted_gauss_ids: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    width: int,
    height: int,
    tiles_x: int,
    w_max_out: wp.array(dtype=float),
):
    """The complexity pass's w_max under W_MAX_ALPHA, scattered: ``w_max_out[y * width + x]`` (filled
    with the floor 1e-4 by the caller) becomes the largest alpha at pixel (x, y) over its tile's
    list, as :func:`complexity_kernel`'s first pass finds it, but walked per list entry instead of
    per pixel. Thread ``local`` of tile ``t``'s block takes the entries ``local``, ``local`` +
    BLOCK_SIZE, ... of the tile's list and evaluates each Gaussian only at the tile's pixels
    inside its support box (:func:`support_box`), where the per-pixel walk evaluates it at all 256:
    a Gaussian a few pixels wide costs a few dozen evaluations instead. The largest alpha does not
    depend on the order, so the result is the walk's, bit for bit where both evaluate alpha alike."""
    tid = wp.tid()
    tile = tid // BLOCK_SIZE
    local = tid - tile * BLOCK_SIZE
    tile_y = tile // tiles_x
    tile_x = tile - tile_y * tiles_x
    tx0 = tile_x * TILE_SIZE
    ty0 = tile_y * TILE_SIZE
    k = tile_ranges[tile, 0] + local
    end = tile_ranges[tile, 1]
    while k < end:
        g = sorted_gauss_ids[k]
        mean = means2d[g]
        conic = conics[g]
        opacity = opacities[g]
        box = support_box(mean, conic, opacity, width, height)
        for y in range(wp.max(box[2], ty0), wp.min(box[3], ty0 + TILE_SIZE - 1) + 1):
            for x in range(wp.max(box[0], tx0), wp.min(box[1], tx0 + TILE_SIZE - 1) + 1):
                index = y * width + x
                if opacity > w_max_out[index]:  # else its alpha (at most its opacity) cannot raise it
                    alpha = splat_alpha(mean, conic, opacity, float(x) + 0.5, float(y) + 0.5)
                    if alpha > 0.0:
                        atomic_max_nonnegative(w_max_out, index, alpha)
        k += BLOCK_SIZE


@wp.func
def complexity_pixel(
    tid: int,
    tile_ranges: wp.array2d(dtype=wp.int32),
    sorted_gauss_ids: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    complexity_map: wp.array2d(dtype=wp.uint8),
    width: int,
    height: int,
    tiles_x: int,
    w_max_rule: int,
    w_max_map: wp.array(dtype=float),
    max_rule: int,
    seed: int,
    sums: int,
    keys: wp.array(dtype=wp.int32),
    max_out: wp.array(dtype=float),
    sum_out: wp.array(dtype=float),
    count_out: wp.array(dtype=wp.int32),
):
    """The work of thread ``tid`` of :func:`complexity_kernel` (its pixel of one view), with the
    kernel's arguments: the one body of that kernel and of :func:`complexity_views_kernel`."""
    pix = tile_pixel(tid, tiles_x)
    x = pix[0]
    y = pix[1]
    local = tid - pix[2] * BLOCK_SIZE
    px = float(x) + 0.5
    py = float(y) + 0.5
    start = tile_ranges[pix[2], 0]
    end = tile_ranges[pix[2], 1]
    staged = on_cuda()
    hf = float(0.0)
    outside = int(1)  # pixels outside the image only help load batches and take part in the warp's collectives
    if x < width and y < height:
        hf = float(complexity_map[y, x]) / 255.0
        outside = 0

    # First pass: w_max, unless given.
    w_max = float(1.0e-4)
    transmittance = float(1.0)  # stays 1 under W_MAX_ALPHA
    stopped = outside  # under W_MAX_WEIGHT: the pixel's compositing has ended
    batch = start
    if w_max_map.shape[0] > 0:  # the same for every thread: no block leaves the walk's collectives half-way
        batch = end
        if outside == 0:
            w_max = w_max_map[y * width + x]
    while batch < end:
        count = wp.min(BLOCK_SIZE, end - batch)
        done = int(0)
        if stopped != 0 or MAX_ALPHA * transmittance <= w_max:
            done = 1
        if staged != 0:
            if block_count(done) >= BLOCK_SIZE:
                break
            if local < count:
                stage_shape(local, sorted_gauss_ids[batch + local], means2d, conics, opacities)
            block_sync()
        if done == 0:
            for j in range(count):
                g = int(0)
                if staged == 0:
                    g = sorted_gauss_ids[batch + j]
                extra = shape_of(staged, 1, j, g, means2d, conics, opacities)
                if w_max_rule == W_MAX_ALPHA and extra[1] <= w_max:
                    continue
                alpha = shape_alpha(shape_of(staged, 0, j, g, means2d, conics, opacities), extra, px, py)
                if alpha == 0.0:
                    continue
                if w_max_rule == W_MAX_ALPHA:
                    w_max = wp.max(w_max, alpha)
                else:
                    next_transmittance = transmittance * (1.0 - alpha)
                    if next_transmittance < MIN_TRANSMITTANCE:  # the blend stops before this one
                        stopped = 1
                        break
                    w_max = wp.max(w_max, alpha * transmittance)
                    transmittance = next_transmittance
                if MAX_ALPHA * transmittance <= w_max:
                    break
        if staged != 0:
            block_sync()  # the batch is read before the next one overwrites it
        elif done != 0 or stopped != 0:
            break
        batch += BLOCK_SIZE

    # Second pass: the warp's lanes walk the list together so that each Gaussian's max, sum and
    # count are combined in registers; the max then meets the block's other warps in shared memory
    # and reaches global memory once per tile (sums and counts once per warp). A lane whose pixel
    # has stopped takes part with nothing; the warp leaves a batch once all its lanes have stopped.
    transmittance = float(1.0)
    stopped = outside
    batch = start
    while batch < end:
        count = wp.min(BLOCK_SIZE, end - batch)
        if staged != 0:
            if block_count(stopped) >= BLOCK_SIZE:
                break
            if local < count:
                stage_shape(local, sorted_gauss_ids[batch + local], means2d, conics, opacities)
            batch_max(BATCH_STORE, local, 0.0)
            block_sync()
        for j in range(count):  # the same for the warp's lanes
            if lane_any(1 - stopped) == 0:
                break
            k = batch + j
            g = int(0)
            if staged != 0:
                g = tile_ids(BATCH_LOAD, j, 0)
            else:
                g = sorted_gauss_ids[k]
            alpha = float(0.0)
            if stopped == 0:
                shape = shape_of(staged, 0, j, g, means2d, conics, opacities)
                alpha = shape_alpha(shape, shape_of(staged, 1, j, g, means2d, conics, opacities), px, py)
            value = float(0.0)
            valid = int(0)
            if alpha > 0.0:
                next_transmittance = transmittance * (1.0 - alpha)
                if next_transmittance < MIN_TRANSMITTANCE:  # the blend stops before this one
                    stopped = 1
                else:
                    value = hf * wp.max(alpha * transmittance, 1.0e-4) / w_max
                    valid = 1
                    transmittance = next_transmittance
            if lane_any(valid) != 0:
                if max_rule == MAX_RACY_RANK:
                    key = int(-1)
                    if valid != 0:
                        key = racy_key(seed, g, local)
                    top_key = lane_max_int(key)
                    if lane_leads() != 0:
                        wp.atomic_max(keys, k, top_key)
                else:
                    kept = value
                    if max_rule == MAX_RACY_KEEP:
                        if valid == 0 or racy_key(seed, g, local) != keys[k]:
                            kept = 0.0
                    top = lane_max(kept)
                    if sums != 0:
                        total = lane_sum(value)
                        hits = lane_sum(float(valid))
                        if lane_leads() != 0:
                            wp.atomic_add(sum_out, g, total)
                            wp.atomic_add(count_out, g, int(hits))
                    if lane_leads() != 0 and top > 0.0:
                        if staged != 0:
                            batch_max(BATCH_MAX, j, top)  # the block's warps combined, added below
                        else:
                            atomic_max_nonnegative(max_out, g, top)  # top >= 0, max_out zeroed by the caller
        if staged != 0:
            block_sync()
            # one atomic per entry of the batch that a pixel of the tile composited, not one per warp
            if local < count and max_rule != MAX_RACY_RANK:
                top = batch_max(BATCH_LOAD, local, 0.0)
                if top > 0.0:
                    atomic_max_nonnegative(max_out, tile_ids(BATCH_LOAD, local, 0), top)
        elif stopped != 0:
            break
        batch += BLOCK_SIZE


@wp.kernel(enable_backward=False)
def complexity_kernel(
    tile_ranges: wp.array2d(dtype=wp.int32),
    sorted_gauss_ids: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    complexity_map: wp.array2d(dtype=wp.uint8),
    width: int,
    height: int,
    tiles_x: int,
    w_max_rule: int,
    w_max_map: wp.array(dtype=float),
    max_rule: int,
    seed: int,
    sums: int,
    keys: wp.array(dtype=wp.int32),
    max_out: wp.array(dtype=float),
    sum_out: wp.array(dtype=float),
    count_out: wp.array(dtype=wp.int32),
):
    """CDC-GS complexity of each Gaussian in one view: max (and sum, count) over the pixels it
    composites of HF(p) * w_i(p) / w_max(p), weights w = alpha * T floored at 1e-4.

    Two passes over each pixel's list, in compositing order, with the forward blend's alpha and
    transmittance rules: a pixel stops before the Gaussian that would take its transmittance
    below MIN_TRANSMITTANCE, as the blend does, so the kernel needs no forward render, only the
    tile lists. The lists are walked in batches of BLOCK_SIZE that the block stages in shared
    memory on CUDA (as the forward blend does). The first pass finds w_max (``w_max_rule``:
    W_MAX_WEIGHT the largest alpha * T up to the pixel's stop, W_MAX_ALPHA the largest alpha over
    the whole tile list, both floored at 1e-4); a pixel leaves it once no later Gaussian can raise
    w_max (alpha <= MAX_ALPHA * T), and under W_MAX_ALPHA skips a Gaussian whose opacity does
    not exceed w_max (alpha <= opacity): both exact. The second combines the warp's contributions
    per Gaussian in registers (one ``__reduce_max_sync`` on sm_80 and later), then on CUDA the
    block's warps in shared memory (``batch_max``), and adds them with an exact atomic max once per
    tile and Gaussian, and with ``sums`` non-zero
    atomic sums and counts too (the mean aggregations read them; with ``sums`` 0 ``sum_out``
    and ``count_out`` are left untouched). ``max_rule`` MAX_RACY_RANK writes, per entry of the
    tile lists, the largest ``racy_key`` (with ``seed``) of the pixels that composite it into
    ``keys`` (as long as ``sorted_gauss_ids``, filled with -1) and nothing else; MAX_RACY_KEEP
    then takes into ``max_out`` only those pixels' values (sums and counts stay exact).
    ``complexity_map`` holds HF in [0, 1] as uint8 (x 255). ``w_max_map``: empty, or every
    pixel's w_max (``y * width + x``) found before (:func:`w_max_alpha_kernel`), which replaces the
    first pass.
    """
    complexity_pixel(
        wp.tid(),
        tile_ranges,
        sorted_gauss_ids,
        means2d,
        conics,
        opacities,
        complexity_map,
        width,
        height,
        tiles_x,
        w_max_rule,
        w_max_map,
        max_rule,
        seed,
        sums,
        keys,
        max_out,
        sum_out,
        count_out,
    )


# The columns of complexity_views_kernel's table: the addresses of a view's tile ranges, tile
# lists, 2D means, conics, opacities and complexity map, the length of its tile lists, then the
# address of its overflow flag (int32; 0: none) and that flag's index there.
VIEW_TABLE_COLUMNS = 9
VIEW_TABLE_MAP = 5  # the column of the complexity map's address


@wp.kernel(enable_backward=False)
def complexity_views_kernel(
    views: wp.array2d(dtype=wp.int64),
    num_gaussians: int,
    width: int,
    height: int,
    tiles_x: int,
    tiles_y: int,
    w_max_rule: int,
    no_w_max_map: wp.array(dtype=float),
    no_keys: wp.array(dtype=wp.int32),
    max_out: wp.array(dtype=float),
    no_sums: wp.array(dtype=float),
    no_counts: wp.array(dtype=wp.int32),
):
    """:func:`complexity_kernel`'s exact max (``max_rule`` MAX_EXACT, no sums, w_max found by the
    walk) of several views of one image size in one launch: ``dim`` = views * tiles * BLOCK_SIZE,
    the blocks of view 0's tiles first. Row ``v`` of ``views`` [V, VIEW_TABLE_COLUMNS] holds the
    addresses of view v's ``tile_ranges`` [tiles, 2] int32, ``sorted_gauss_ids`` int32 (its length
    in column 6), ``means2d`` [N] vec2, ``conics`` [N] vec3, ``opacities`` [N] float32 and
    ``complexity_map`` [height, width] uint8, as ``complexity_kernel`` takes them (N =
    ``num_gaussians``, the same Gaussians in every view). Every view's maxima go into ``max_out``
    [N], a maximum over the views as the views one launch at a time give it, bit for bit (a max
    does not depend on the order). A launch of one view keeps the SMs that its last, longest tile
    lists leave idle waiting; here the next views' tiles take them. A view binned into slots may
    name its overflow flag (columns 7 and 8: the address of an int32 array and the flag's index in
    it, as a render's ``pending`` holds it): when it is set, the view's lists are incomplete and
    it adds nothing (its threads leave at once). The ``no_`` arrays: empty (length 0, and 1 for the
    sums and counts), as complexity_kernel's unused arguments."""
    tid = wp.tid()
    per_view = tiles_x * tiles_y * BLOCK_SIZE
    v = tid // per_view
    if views[v, 7] != wp.int64(0):  # the same for every thread of the view: none is left in a collective
        flag = int(views[v, 8])
        overflow = wp.array(ptr=wp.uint64(views[v, 7]), shape=(flag + 1,), dtype=wp.int32)
        if overflow[flag] != 0:
            return
    tile_ranges = wp.array(ptr=wp.uint64(views[v, 0]), shape=(tiles_x * tiles_y, 2), dtype=wp.int32)
    sorted_gauss_ids = wp.array(ptr=wp.uint64(views[v, 1]), shape=(int(views[v, 6]),), dtype=wp.int32)
    means2d = wp.array(ptr=wp.uint64(views[v, 2]), shape=(num_gaussians,), dtype=wp.vec2)
    conics = wp.array(ptr=wp.uint64(views[v, 3]), shape=(num_gaussians,), dtype=wp.vec3)
    opacities = wp.array(ptr=wp.uint64(views[v, 4]), shape=(num_gaussians,), dtype=float)
    complexity_map = wp.array(ptr=wp.uint64(views[v, 5]), shape=(height, width), dtype=wp.uint8)
    complexity_pixel(
        tid - v * per_view,
        tile_ranges,
        sorted_gauss_ids,
        means2d,
        conics,
        opacities,
        complexity_map,
        width,
        height,
        tiles_x,
        w_max_rule,
        no_w_max_map,
        MAX_EXACT,
        0,
        0,
        no_keys,
        max_out,
        no_sums,
        no_counts,
    )
