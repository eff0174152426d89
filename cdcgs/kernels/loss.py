"""The training loss, (1 - w) L1 + w (1 - SSIM), fused: two separable passes forward, two backward.

Pure Warp. SSIM as kornia computes it (``kornia.metrics.ssim(..., window_size=11)``): an 11-tap
Gaussian window (sigma 1.5, normalised), reflect padding (index -1 reads 1), c1 = 0.01^2,
c2 = 0.03^2 and 1e-12 added to the denominator; the L1 term as torch's ``(x - y).abs().mean()``,
whose gradient is 0 where x equals y. Both are means over every pixel and channel.

``image`` is an [H, W] array of ``wp.vec3`` in [0, 1]; ``target`` an [H, W, 3] array of uint8
(read as value / 255) or float32. Every kernel takes one thread per pixel, in row-major order.

The window is separable, w(ky, kx) = g(ky) g(kx), and so is the reflect padding (it reflects
rows and columns independently). Each side is therefore a horizontal pass of 11 taps into a
scratch array and a vertical pass of 11 taps over it: 22 taps a pixel instead of 121.

Forward, in this order:

- ``ssim_l1_forward_rows_kernel``: ``dim=H * W``. Writes ``row_moments`` [5, H, W] of vec3: per
  pixel and channel the sums along the row, weighted by g, of x, y, x^2, y^2 and xy (x the image,
  y the target), in that order. Not needed when w is 0 (the next kernel does not read it then).
- ``ssim_l1_forward_kernel``: launch with ``dim=ssim_l1_launch_size(H, W)`` (a whole number of
  CUDA warps: the threads past H * W add nothing but must exist for the warp sums). Sums 11 rows of
  ``row_moments`` into the window's moments, adds the loss and the mean squared error of the image
  clamped to [0, 1] (for the PSNR) into ``sums[0]`` and ``sums[1]`` (zero them first), and writes
  per pixel and channel the three derivatives of SSIM that the backward needs: with respect to the
  window's mean of the image (the moments E[x^2] and E[xy] held fixed), to E[x^2] and to E[xy].

Backward, in this order (the gradient of ``grad_loss[0] * loss`` with respect to the image). A
pixel enters every window within 5 pixels of it, once more through the reflection where a window
crosses the border; the backward gathers the three derivative maps over those windows with the
matching weights, so no pixel is written twice (no atomics):

- ``ssim_l1_backward_rows_kernel``: ``dim=H * W``. Gathers the three maps along the row, writing
  ``row_gathers`` [3, H, W] of vec3 (the mean, E[x^2] and E[xy] maps, in that order). Not needed
  when w is 0.
- ``ssim_l1_backward_kernel``: ``dim=H * W``. Gathers ``row_gathers`` along the column and writes
  (does not add) the gradient into ``grad_image``.
"""

from typing import Any

import numpy as np
import warp as wp

from ._lanes import lane_leads, lane_sum

# The windows as loops: unrolled, the CPU build of the former 11 x 11 loops took minutes. The
# backward is written by hand, so Warp's generated adjoints would only lengthen the build.
wp.set_module_options({"max_unroll": 1, "enable_backward": False})

__all__ = [
    "ROW_GATHERS",
    "ROW_MOMENTS",
    "SSIM_RADIUS",
    "SSIM_SIGMA",
    "ssim_l1_backward_kernel",
    "ssim_l1_backward_rows_kernel",
    "ssim_l1_forward_kernel",
    "ssim_l1_forward_rows_kernel",
    "ssim_l1_launch_size",
    "ssim_weights",
]

SSIM_RADIUS = 5  # an 11-tap window, kornia's window_size=11
SSIM_SIGMA = 1.5
_C1 = wp.constant(0.01**2)
_C2 = wp.constant(0.03**2)
_EPS = wp.constant(1.0e-12)  # kornia's eps in the denominator


def ssim_weights() -> np.ndarray:
    """The normalised 1-D window, float64 (kornia's ``get_gaussian_kernel1d(11, 1.5)``)."""
    d = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=np.float64)
    g = np.exp(-(d**2) / (2.0 * SSIM_SIGMA**2))
    return g / g.sum()


_window = wp.types.vector(length=2 * SSIM_RADIUS + 1, dtype=wp.float32)
_WEIGHTS = wp.constant(_window(*ssim_weights().astype(np.float32).tolist()))
_RADIUS = wp.constant(SSIM_RADIUS)
_TAPS = wp.constant(2 * SSIM_RADIUS + 1)

# The slices of the scratch arrays: ``row_moments`` [ROW_MOMENTS, H, W] (the forward's) and
# ``row_gathers`` [ROW_GATHERS, H, W] (the backward's).
ROW_MOMENTS = 5
_MEAN_X = wp.constant(0)
_MEAN_Y = wp.constant(1)
_SQUARE_X = wp.constant(2)
_SQUARE_Y = wp.constant(3)
_CROSS = wp.constant(4)
ROW_GATHERS = 3
_GATHER_MEAN = wp.constant(0)
_GATHER_SQUARE = wp.constant(1)
_GATHER_CROSS = wp.constant(2)


def ssim_l1_launch_size(height: int, width: int) -> int:
    """Threads of the ``ssim_l1_forward_kernel`` launch: H * W rounded up to whole 32-thread warps."""
    return -(-height * width // 32) * 32


@wp.func
def _reflect(i: int, n: int) -> int:
    if i < 0:
        return -i
    if i >= n:
        return 2 * (n - 1) - i
    return i


@wp.func
def _unit(v: wp.uint8) -> float:
    return float(v) / 255.0


@wp.func
def _unit(v: float) -> float:
    return v


@wp.func
def _pixel(target: wp.array3d(dtype=Any), y: int, x: int) -> wp.vec3:
    return wp.vec3(_unit(target[y, x, 0]), _unit(target[y, x, 1]), _unit(target[y, x, 2]))


@wp.func
def _sign(v: float) -> float:
    if v > 0.0:
        return 1.0
    if v < 0.0:
        return -1.0
    return 0.0


@wp.kernel
def ssim_l1_forward_rows_kernel(
    image: wp.array2d(dtype=wp.vec3),
    target: wp.array3d(dtype=Any),
    row_moments: wp.array3d(dtype=wp.vec3),
):
    """The horizontal pass: the five moments summed along the row with the window's weights."""
    i = wp.tid()
    width = image.shape[1]
    py = i // width
    px = i - py * width
    mx = wp.vec3(0.0)
    my = wp.vec3(0.0)
    sxx = wp.vec3(0.0)
    syy = wp.vec3(0.0)
    sxy = wp.vec3(0.0)
    for kx in range(_TAPS):
        sx = _reflect(px + kx - _RADIUS, width)
        w = _WEIGHTS[kx]
        a = image[py, sx]
        b = _pixel(target, py, sx)
        mx += w * a
        my += w * b
        sxx += w * wp.cw_mul(a, a)
        syy += w * wp.cw_mul(b, b)
        sxy += w * wp.cw_mul(a, b)
    row_moments[_MEAN_X, py, px] = mx
    row_moments[_MEAN_Y, py, px] = my
    row_moments[_SQUARE_X, py, px] = sxx
    row_moments[_SQUARE_Y, py, px] = syy
    row_moments[_CROSS, py, px] = sxy


@wp.kernel
def ssim_l1_forward_kernel(
    image: wp.array2d(dtype=wp.vec3),
    target: wp.array3d(dtype=Any),
    ssim_weight: float,
    inv_count: float,  # 1 / (3 H W)
    row_moments: wp.array3d(dtype=wp.vec3),
    sums: wp.array(dtype=wp.float32),
    dssim_dmean: wp.array2d(dtype=wp.vec3),
    dssim_dsquare: wp.array2d(dtype=wp.vec3),
    dssim_dcross: wp.array2d(dtype=wp.vec3),
):
    """The vertical pass: the window's moments from 11 rows of ``row_moments``, SSIM, the L1 and the
    squared error; their sums, and the derivative maps of SSIM."""
    i = wp.tid()
    height = image.shape[0]
    width = image.shape[1]
    loss = float(0.0)
    squared = float(0.0)
    if i < height * width:
        py = i // width
        px = i - py * width
        x = image[py, px]
        y = _pixel(target, py, px)
        d = x - y
        l1 = wp.abs(d[0]) + wp.abs(d[1]) + wp.abs(d[2])
        e = wp.vec3(wp.clamp(x[0], 0.0, 1.0), wp.clamp(x[1], 0.0, 1.0), wp.clamp(x[2], 0.0, 1.0)) - y
        squared = wp.dot(e, e)
        loss = l1
        if ssim_weight != 0.0:
            mx = wp.vec3(0.0)
            my = wp.vec3(0.0)
            sxx = wp.vec3(0.0)
            syy = wp.vec3(0.0)
            sxy = wp.vec3(0.0)
            for ky in range(_TAPS):
                sy = _reflect(py + ky - _RADIUS, height)
                w = _WEIGHTS[ky]
                mx += w * row_moments[_MEAN_X, sy, px]
                my += w * row_moments[_MEAN_Y, sy, px]
                sxx += w * row_moments[_SQUARE_X, sy, px]
                syy += w * row_moments[_SQUARE_Y, sy, px]
                sxy += w * row_moments[_CROSS, sy, px]
            c1 = wp.vec3(_C1)
            c2 = wp.vec3(_C2)
            var_x = sxx - wp.cw_mul(mx, mx)
            var_y = syy - wp.cw_mul(my, my)
            cov = sxy - wp.cw_mul(mx, my)
            lum = 2.0 * wp.cw_mul(mx, my) + c1  # numerator factors
            con = 2.0 * cov + c2
            lum_d = wp.cw_mul(mx, mx) + wp.cw_mul(my, my) + c1  # denominator factors
            con_d = var_x + var_y + c2
            den = wp.cw_mul(lum_d, con_d) + wp.vec3(_EPS)
            s = wp.cw_div(wp.cw_mul(lum, con), den)
            # dS/dmean_x with var_x, cov held; dS/dvar_x; dS/dcov.
            d_mean = wp.cw_div(2.0 * wp.cw_mul(my, con) - 2.0 * wp.cw_mul(wp.cw_mul(s, mx), con_d), den)
            d_var = -wp.cw_div(wp.cw_mul(s, lum_d), den)
            d_cov = wp.cw_div(2.0 * lum, den)
            # The same with the raw moments held (var_x = E[x^2] - mean_x^2, cov = E[xy] - mean_x mean_y).
            dssim_dmean[py, px] = d_mean - 2.0 * wp.cw_mul(mx, d_var) - wp.cw_mul(my, d_cov)
            dssim_dsquare[py, px] = d_var
            dssim_dcross[py, px] = d_cov
            loss = (1.0 - ssim_weight) * l1 + ssim_weight * (3.0 - s[0] - s[1] - s[2])
    loss = lane_sum(loss)
    squared = lane_sum(squared)
    if lane_leads():
        wp.atomic_add(sums, 0, loss * inv_count)
        wp.atomic_add(sums, 1, squared * inv_count)


# The backward passes are the transpose of the forward's reads, tap by tap: for each tap k, the
# windows that read the pixel with it. The weight is then the table's entry k, an index the CUDA
# compiler folds once it unrolls the loop. Summing a pixel's weights per window instead (direct and
# reflected) indexes the table with values known only at run time, which puts the table in local
# memory, stored anew at every call: 121 local stores a thread in each backward pass.


@wp.func
def _window_centres(p: int, k: int, n: int) -> wp.vec3i:
    """The centres of the windows whose tap k reads pixel p, along an axis of n >= 6 pixels: the
    one that reads it directly, the one that reads index -p (reflected to p) and the one that reads
    index 2 (n - 1) - p (reflected to p); negative where there is none."""
    direct = p + _RADIUS - k
    if direct >= n:
        direct = -1
    left = -1
    if p > 0:
        left = _RADIUS - k - p  # at most 4: below n
    right = -1
    if p < n - 1:
        right = 2 * (n - 1) - p + _RADIUS - k
        if right >= n:
            right = -1
    return wp.vec3i(direct, left, right)


@wp.kernel
def ssim_l1_backward_rows_kernel(
    dssim_dmean: wp.array2d(dtype=wp.vec3),
    dssim_dsquare: wp.array2d(dtype=wp.vec3),
    dssim_dcross: wp.array2d(dtype=wp.vec3),
    row_gathers: wp.array3d(dtype=wp.vec3),
):
    """The horizontal pass of the backward: each derivative map gathered along the row over the
    windows that hold the pixel's column."""
    i = wp.tid()
    width = dssim_dmean.shape[1]
    qy = i // width  # the row of the windows' centres
    px = i - qy * width
    acc_mean = wp.vec3(0.0)
    acc_square = wp.vec3(0.0)
    acc_cross = wp.vec3(0.0)
    for kx in range(_TAPS):
        w = _WEIGHTS[kx]
        centres = _window_centres(px, kx, width)
        for r in range(3):
            qx = centres[r]
            if qx >= 0:
                acc_mean += w * dssim_dmean[qy, qx]
                acc_square += w * dssim_dsquare[qy, qx]
                acc_cross += w * dssim_dcross[qy, qx]
    row_gathers[_GATHER_MEAN, qy, px] = acc_mean
    row_gathers[_GATHER_SQUARE, qy, px] = acc_square
    row_gathers[_GATHER_CROSS, qy, px] = acc_cross


@wp.kernel
def ssim_l1_backward_kernel(
    image: wp.array2d(dtype=wp.vec3),
    target: wp.array3d(dtype=Any),
    ssim_weight: float,
    inv_count: float,
    grad_loss: wp.array(dtype=wp.float32),
    row_gathers: wp.array3d(dtype=wp.vec3),
    grad_image: wp.array2d(dtype=wp.vec3),
):
    """The vertical pass of the backward: ``row_gathers`` gathered along the column, and the
    gradient of the loss with respect to the image from it and from the L1 term."""
    i = wp.tid()
    height = image.shape[0]
    width = image.shape[1]
    py = i // width
    px = i - py * width
    x = image[py, px]
    y = _pixel(target, py, px)
    d = x - y
    g = grad_loss[0] * inv_count
    grad = (g * (1.0 - ssim_weight)) * wp.vec3(_sign(d[0]), _sign(d[1]), _sign(d[2]))
    if ssim_weight != 0.0:
        acc_mean = wp.vec3(0.0)
        acc_square = wp.vec3(0.0)
        acc_cross = wp.vec3(0.0)
        for ky in range(_TAPS):
            w = _WEIGHTS[ky]
            centres = _window_centres(py, ky, height)
            for r in range(3):
                qy = centres[r]
                if qy >= 0:
                    acc_mean += w * row_gathers[_GATHER_MEAN, qy, px]
                    acc_square += w * row_gathers[_GATHER_SQUARE, qy, px]
                    acc_cross += w * row_gathers[_GATHER_CROSS, qy, px]
        ds_dx = acc_mean + 2.0 * wp.cw_mul(x, acc_square) + wp.cw_mul(y, acc_cross)
        grad -= (g * ssim_weight) * ds_dx
    grad_image[py, px] = grad


for _dtype in (wp.uint8, wp.float32):
    wp.overload(ssim_l1_forward_rows_kernel, {"target": wp.array3d(dtype=_dtype)})
    wp.overload(ssim_l1_forward_kernel, {"target": wp.array3d(dtype=_dtype)})
    wp.overload(ssim_l1_backward_kernel, {"target": wp.array3d(dtype=_dtype)})
