"""The densification statistics of one render, added in one launch.

Pure Warp. After a view's backward pass, 3DGS's adaptive density control adds, for every Gaussian
the view sees (both radii > 0), the norm of its screen-space positional gradient in NDC units
(the pixel-space gradient times W/2 in x and H/2 in y; with AbsGS, the per-pixel absolute sums
instead) to a running sum, 1 to a view count, and takes the largest pixel radius into a running
maximum. ``accumulate_statistics_kernel`` (``dim=N``) does the three in place, where torch took
about fifteen small launches.
"""

import warp as wp

__all__ = ["accumulate_statistics_kernel"]

wp.set_module_options({"fast_math": False})


@wp.kernel(enable_backward=False)
def accumulate_statistics_kernel(
    gradient: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.vec2i),
    half_width: float,
    half_height: float,
    grad_sum: wp.array(dtype=float),
    count: wp.array(dtype=float),
    max_radius: wp.array(dtype=float),
    halt: wp.array(dtype=wp.int32),
):
    """For Gaussian ``i`` with both radii > 0: ``grad_sum[i] += |(g.x W/2, g.y H/2)|``,
    ``count[i] += 1``, ``max_radius[i] = max(max_radius[i], max(radii[i]))``; the others as they
    are. Nothing while ``halt[0]`` is non-zero (``halt`` empty: never; see ``fused_adam_kernel``)."""
    i = wp.tid()
    if halt.shape[0] > 0:
        if halt[0] != 0:
            return
    r = radii[i]
    if r[0] <= 0 or r[1] <= 0:
        return
    g = gradient[i]
    x = g[0] * half_width
    y = g[1] * half_height
    grad_sum[i] = grad_sum[i] + wp.sqrt(x * x + y * y)
    count[i] = count[i] + 1.0
    max_radius[i] = wp.max(max_radius[i], float(wp.max(r[0], r[1])))
