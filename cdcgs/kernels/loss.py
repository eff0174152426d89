"""The training loss, (1 - w) L1 + w (1 - SSIM), fused: one forward and one backward kernel.

Pure Warp. SSIM as kornia computes it (``kornia.metrics.ssim(..., window_size=11)``): an 11-tap
Gaussian window (sigma 1.5, normalised), reflect padding (index -1 reads 1), c1 = 0.01^2,
c2 = 0.03^2 and 1e-12 added to the denominator; the L1 term as torch's ``(x - y).abs().mean()``,
whose gradient is 0 where x equals y. Both are means over every pixel and channel.

``image`` is an [H, W] array of ``wp.vec3`` in [0, 1]; ``target`` an [H, W, 3] array of uint8
(read as value / 255) or float32. Both kernels take one thread per pixel.

- ``ssim_l1_forward_kernel``: launch with ``dim=ssim_l1_launch_size(H, W)`` (a whole number of
  CUDA warps: the threads past H * W add nothing but must exist for the warp sums). It adds the
  loss and the mean squared error of the image clamped to [0, 1] (for the PSNR) into
  ``sums[0]`` and ``sums[1]`` (zero them first), and writes per pixel and channel the three
  derivatives of SSIM that the backward pass needs: with respect to the window's mean of the image
  (the moments E[x^2] and E[xy] held fixed), to E[x^2] and to E[xy].
- ``ssim_l1_backward_kernel``: ``dim=H * W``; the gradient of ``grad_loss[0] * loss`` with respect to
  the image, written (not added) into ``grad_image``. A pixel enters every window within 5 pixels
  of it, once more through the reflection where a window crosses the border; the kernel gathers
  the three derivative maps over those windows with the matching weights, so no pixel is written
  twice (no atomics).
"""

from typing import Any

import numpy as np
import warp as wp

from ._lanes import lane_leads, lane_sum

wp.set_module_options({"max_unroll": 1})  # the 11 x 11 window as loops: unrolled, the CPU build took minutes

__all__ = [
    "SSIM_RADIUS",
    "SSIM_SIGMA",
    "ssim_l1_backward_kernel",
    "ssim_l1_forward_kernel",
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


def ssim_l1_launch_size(height: int, width: int) -> int:
    """Threads of the forward launch: H * W rounded up to whole 32-thread warps."""
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
def ssim_l1_forward_kernel(
    image: wp.array2d(dtype=wp.vec3),
    target: wp.array3d(dtype=Any),
    ssim_weight: float,
    inv_count: float,  # 1 / (3 H W)
    sums: wp.array(dtype=wp.float32),
    dssim_dmean: wp.array2d(dtype=wp.vec3),
    dssim_dsquare: wp.array2d(dtype=wp.vec3),
    dssim_dcross: wp.array2d(dtype=wp.vec3),
):
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
                wy = _WEIGHTS[ky]
                for kx in range(_TAPS):
                    sx = _reflect(px + kx - _RADIUS, width)
                    w = wy * _WEIGHTS[kx]
                    a = image[sy, sx]
                    b = _pixel(target, sy, sx)
                    mx += w * a
                    my += w * b
                    sxx += w * wp.cw_mul(a, a)
                    syy += w * wp.cw_mul(b, b)
                    sxy += w * wp.cw_mul(a, b)
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


@wp.func
def _tap_weight(q: int, p: int, n: int) -> float:
    """Total weight with which pixel p enters the window centred on q (|q - p| <= radius), the
    reflections across either border included."""
    w = _WEIGHTS[p - q + _RADIUS]
    if p > 0:
        k = _RADIUS - p - q  # q + k - radius = -p, reflected to p
        if k >= 0:
            w += _WEIGHTS[k]
    if p < n - 1:
        k = 2 * (n - 1) - p - q + _RADIUS  # q + k - radius = 2 (n - 1) - p, reflected to p
        if k < _TAPS:
            w += _WEIGHTS[k]
    return w


@wp.kernel
def ssim_l1_backward_kernel(
    image: wp.array2d(dtype=wp.vec3),
    target: wp.array3d(dtype=Any),
    ssim_weight: float,
    inv_count: float,
    grad_loss: wp.array(dtype=wp.float32),
    dssim_dmean: wp.array2d(dtype=wp.vec3),
    dssim_dsquare: wp.array2d(dtype=wp.vec3),
    dssim_dcross: wp.array2d(dtype=wp.vec3),
    grad_image: wp.array2d(dtype=wp.vec3),
):
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
            qy = py + ky - _RADIUS
            if qy >= 0 and qy < height:
                wy = _tap_weight(qy, py, height)
                for kx in range(_TAPS):
                    qx = px + kx - _RADIUS
                    if qx >= 0 and qx < width:
                        w = wy * _tap_weight(qx, px, width)
                        acc_mean += w * dssim_dmean[qy, qx]
                        acc_square += w * dssim_dsquare[qy, qx]
                        acc_cross += w * dssim_dcross[qy, qx]
        ds_dx = acc_mean + 2.0 * wp.cw_mul(x, acc_square) + wp.cw_mul(y, acc_cross)
        grad -= (g * ssim_weight) * ds_dx
    grad_image[py, px] = grad


for _dtype in (wp.uint8, wp.float32):
    wp.overload(ssim_l1_forward_kernel, {"target": wp.array3d(dtype=_dtype)})
    wp.overload(ssim_l1_backward_kernel, {"target": wp.array3d(dtype=_dtype)})
