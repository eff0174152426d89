"""World to screen: EWA projection of 3D Gaussians and their spherical-harmonics colour.

Pure Warp. Conventions: world-to-camera matrices, camera x right, y down, z forward (COLMAP);
quaternions (w, x, y, z); pixel coordinates continuous with pixel (i, j) centred at (i + 0.5, j + 0.5).

The projection's backward pass is Warp's generated adjoint (launch with ``adjoint=True``); the SH
colour's is written out (``sh_to_color_backward_kernel``: plain stores instead of the generated
adjoint's atomics; ``sh_to_color_kernel``'s generated adjoint stays exact for ``wp.Tape`` users).
Tests check both against a float64 reference.
"""

import warp as wp

from ._constants import MAX_SH_COEFFICIENTS, SH_C0, SH_C1, SH_C2, SH_C3
from ._lanes import GROUP_SIZE, block_sync, group_read
from .adam import AdamStep, adam_step_halted, adam_step_rates, adam_step_value, adam_step_with

__all__ = [
    "ALPHA_THRESHOLD",
    "SH_BLOCK",
    "Camera",
    "make_camera",
    "project_gaussians_kernel",
    "sh_to_color_backward_kernel",
    "sh_to_color_grouped_backward_kernel",
    "sh_to_color_kernel",
    "sh_to_color_staged_backward_kernel",
]

# CUDA: --use_fast_math (approximate exp, division and square root, as gsplat builds its kernels);
# the CPU build ignores the option.
wp.set_module_options({"fast_math": True})

# Alpha below this never composites (3DGS).
ALPHA_THRESHOLD = wp.constant(1.0 / 255.0)
# Added to the diagonal of every 2D covariance, in px^2 (3DGS low-pass filter).
COVARIANCE_DILATION = wp.constant(0.3)
# Camera-space x/z and y/z are clamped to this multiple of the field-of-view limits in the Jacobian.
FRUSTUM_CLAMP = wp.constant(1.3)
# A footprint larger than this (px) is clamped before conversion to integers.
MAX_RADIUS = wp.constant(1.0e8)

# The SH constants of _constants.py one by one: Warp kernels read numbers, not tuples.
SH_C2_0, SH_C2_1, SH_C2_2, SH_C2_3, SH_C2_4 = SH_C2
SH_C3_0, SH_C3_1, SH_C3_2, SH_C3_3, SH_C3_4, SH_C3_5, SH_C3_6 = SH_C3

mat23 = wp.types.matrix(shape=(2, 3), dtype=wp.float32)


@wp.struct
class Camera:
    """A pinhole camera: world-to-camera rotation and translation, intrinsics in pixels, image size."""

    rotation: wp.mat33
    translation: wp.vec3
    center: wp.vec3  # camera centre in world coordinates, -R^T t
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    near: float


@wp.func
def camera_of(camera: Camera, camera_on_device: wp.array(dtype=Camera)):
    """``camera``, or with a non-empty ``camera_on_device`` that array's entry 0."""
    if camera_on_device.shape[0] > 0:
        return camera_on_device[0]
    return camera


@wp.func_grad(camera_of)
def adj_camera_of(camera: Camera, camera_on_device: wp.array(dtype=Camera), adj_ret: Camera):
    """No gradient reaches the camera: without this adjoint a kernel's autodiff keeps a Camera of
    adjoints for each source (the projection's adjoint rose from 119 to 156 registers, and took
    50% longer on an H100)."""
    pass


def make_camera(viewmat, intrinsics, width: int, height: int, near: float = 0.01) -> Camera:
    """Build a :class:`Camera` from a 4x4 world-to-camera matrix and a 3x3 intrinsic matrix.

    Both are anything numpy can read as float64 arrays (nested lists, numpy, CPU torch tensors).
    """
    import numpy as np

    view = np.asarray(viewmat, dtype=np.float64)
    K = np.asarray(intrinsics, dtype=np.float64)
    cam = Camera()
    rotation = view[:3, :3]
    translation = view[:3, 3]
    cam.rotation = wp.mat33(*rotation.reshape(-1).tolist())
    cam.translation = wp.vec3(*translation.tolist())
    cam.center = wp.vec3(*(-rotation.T @ translation).tolist())
    cam.fx, cam.fy, cam.cx, cam.cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    cam.width, cam.height, cam.near = int(width), int(height), float(near)
    return cam


@wp.func
def quat_to_rotation(q: wp.vec4):
    """Rotation matrix of the quaternion (w, x, y, z), normalised here."""
    n = q / wp.length(q)
    w = n[0]
    x = n[1]
    y = n[2]
    z = n[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def write_culled(
    i: int,
    means2d_out: wp.array(dtype=wp.vec2),
    conics_out: wp.array(dtype=wp.vec3),
    depths_out: wp.array(dtype=float),
    opacities_out: wp.array(dtype=float),
    radii_out: wp.array(dtype=wp.vec2i),
):
    """Zeros for a culled Gaussian (radius 0), so that the outputs need no zero fill beforehand."""
    means2d_out[i] = wp.vec2(0.0, 0.0)
    conics_out[i] = wp.vec3(0.0, 0.0, 0.0)
    depths_out[i] = 0.0
    opacities_out[i] = 0.0
    radii_out[i] = wp.vec2i(0, 0)


@wp.kernel
def project_gaussians_kernel(
    gauss_means: wp.array(dtype=wp.vec3),
    gauss_quats: wp.array(dtype=wp.vec4),
    gauss_scales: wp.array(dtype=wp.vec3),
    gauss_opacities: wp.array(dtype=float),
    camera: Camera,
    camera_on_device: wp.array(dtype=Camera),
    antialiased: int,
    means2d_out: wp.array(dtype=wp.vec2),
    conics_out: wp.array(dtype=wp.vec3),
    depths_out: wp.array(dtype=float),
    opacities_out: wp.array(dtype=float),
    radii_out: wp.array(dtype=wp.vec2i),
    nonfinite_out: wp.array(dtype=wp.int32),
):
    """EWA-project one Gaussian: pixel mean, conic, depth, opacity and per-axis pixel radius.

    Every output is written: a culled Gaussian gets radius 0 and zeros. ``nonfinite_out``
    (optional, None skips the check): entry k is set to 1 when a Gaussian's mean (k = 0),
    quaternion (1), scales (2) or opacity (3) hold a NaN or an infinity, so validating them costs no
    read of their own; a shorter array's last entry takes the inputs beyond it (an int32 [1]:
    "some input is non-finite").

    The camera is ``camera``, or with a non-empty ``camera_on_device`` that array's entry 0, which
    a kernel may write between launches (a step replayed as a CUDA graph picks its view on the
    device; every camera it holds must have ``camera``'s image size).
    """
    i = wp.tid()
    cam = camera_of(camera, camera_on_device)
    flags = nonfinite_out.shape[0]
    if flags > 0:
        # every writer writes 1: no atomics needed
        if not wp.isfinite(gauss_means[i]):
            nonfinite_out[0] = 1
        if not wp.isfinite(gauss_quats[i]):
            nonfinite_out[wp.min(1, flags - 1)] = 1
        if not wp.isfinite(gauss_scales[i]):
            nonfinite_out[wp.min(2, flags - 1)] = 1
        if not wp.isfinite(gauss_opacities[i]):
            nonfinite_out[wp.min(3, flags - 1)] = 1
    p = cam.rotation * gauss_means[i] + cam.translation
    if p[2] < cam.near:
        write_culled(i, means2d_out, conics_out, depths_out, opacities_out, radii_out)
        return

    rotation = quat_to_rotation(gauss_quats[i])
    s = gauss_scales[i]
    m = rotation * wp.diag(s)
    cov_world = m * wp.transpose(m)
    cov_cam = cam.rotation * cov_world * wp.transpose(cam.rotation)

    # Perspective Jacobian at a point clamped to 1.3x the field of view (keeps off-screen
    # Gaussians from exploding); the mean itself is projected unclamped.
    inv_z = 1.0 / p[2]
    lim_left = FRUSTUM_CLAMP * cam.cx / cam.fx
    lim_right = FRUSTUM_CLAMP * (float(cam.width) - cam.cx) / cam.fx
    lim_top = FRUSTUM_CLAMP * cam.cy / cam.fy
    lim_bottom = FRUSTUM_CLAMP * (float(cam.height) - cam.cy) / cam.fy
    tx = wp.clamp(p[0] * inv_z, -lim_left, lim_right) * p[2]
    ty = wp.clamp(p[1] * inv_z, -lim_top, lim_bottom) * p[2]
    jac = mat23(
        cam.fx * inv_z,
        0.0,
        -cam.fx * tx * inv_z * inv_z,
        0.0,
        cam.fy * inv_z,
        -cam.fy * ty * inv_z * inv_z,
    )
    cov2d = jac * cov_cam * wp.transpose(jac)

    a0 = cov2d[0, 0]
    b = 0.5 * (cov2d[0, 1] + cov2d[1, 0])
    c0 = cov2d[1, 1]
    det_raw = a0 * c0 - b * b
    a = a0 + COVARIANCE_DILATION
    c = c0 + COVARIANCE_DILATION
    det = a * c - b * b
    if det <= 0.0:
        write_culled(i, means2d_out, conics_out, depths_out, opacities_out, radii_out)
        return

    opacity = gauss_opacities[i]
    if antialiased != 0:
        # Mip-Splatting: keep the integrated opacity of the Gaussian after dilation.
        ratio = det_raw / det
        if ratio > 0.0:
            opacity = opacity * wp.sqrt(ratio)
        else:
            opacity = 0.0
    if opacity * 255.0 <= 1.0:
        # alpha = opacity * exp(power) <= opacity can never reach 1/255
        write_culled(i, means2d_out, conics_out, depths_out, opacities_out, radii_out)
        return

    # Exact bounding box of {d : opacity * exp(-d^T conic d / 2) >= 1/255}: the 3DGS 3-sigma
    # footprint made exact (at most 3.33 sigma, less for transparent Gaussians), so tiling never
    # drops a pixel that a dense renderer composites.
    extent = wp.sqrt(2.0 * wp.log(opacity * 255.0))
    radius_x = wp.min(extent * wp.sqrt(a), MAX_RADIUS)
    radius_y = wp.min(extent * wp.sqrt(c), MAX_RADIUS)
    mean2d = wp.vec2(cam.fx * p[0] * inv_z + cam.cx, cam.fy * p[1] * inv_z + cam.cy)
    if (
        mean2d[0] + radius_x <= 0.0
        or mean2d[0] - radius_x >= float(cam.width)
        or mean2d[1] + radius_y <= 0.0
        or mean2d[1] - radius_y >= float(cam.height)
    ):
        write_culled(i, means2d_out, conics_out, depths_out, opacities_out, radii_out)
        return

    means2d_out[i] = mean2d
    conics_out[i] = wp.vec3(c / det, -b / det, a / det)
    depths_out[i] = p[2]
    opacities_out[i] = opacity
    radii_out[i] = wp.vec2i(int(wp.ceil(radius_x)), int(wp.ceil(radius_y)))


@wp.func
def sh_coefficient(gauss_sh: wp.array2d(dtype=wp.vec3), gauss_sh_rest: wp.array2d(dtype=wp.vec3), i: int, j: int):
    """Coefficient j of Gaussian i: from ``gauss_sh`` [N, K] alone, or, when ``gauss_sh_rest`` is
    given (not empty), the degree-0 one from ``gauss_sh`` [N, 1] and the others from
    ``gauss_sh_rest`` [N, K - 1] (the two tensors a trainer keeps, no concatenation)."""
    if j == 0 or gauss_sh_rest.shape[0] == 0:
        return gauss_sh[i, j]
    return gauss_sh_rest[i, j - 1]


@wp.func
def sh_stored(gauss_sh: wp.array2d(dtype=wp.vec3), gauss_sh_rest: wp.array2d(dtype=wp.vec3)) -> int:
    """Coefficients stored per Gaussian, over the one or two arrays."""
    if gauss_sh_rest.shape[0] == 0:
        return gauss_sh.shape[1]
    return 1 + gauss_sh_rest.shape[1]


@wp.func
def store_sh_gradient(
    grad_sh_out: wp.array2d(dtype=wp.vec3), grad_sh_rest_out: wp.array2d(dtype=wp.vec3), i: int, j: int, value: wp.vec3
):
    """Write coefficient j's gradient where :func:`sh_coefficient` reads it."""
    if j == 0 or grad_sh_rest_out.shape[0] == 0:
        grad_sh_out[i, j] = value
    else:
        grad_sh_rest_out[i, j - 1] = value


@wp.func
def give_sh_gradient(
    grad_sh_out: wp.array2d(dtype=wp.vec3),
    grad_sh_rest_out: wp.array2d(dtype=wp.vec3),
    dc_step: AdamStep,
    rest_step: AdamStep,
    i: int,
    j: int,
    rest_count: int,
    value: wp.vec3,
):
    """Coefficient j's gradient ``value``: written where :func:`sh_coefficient` reads the
    coefficient, or, with the steps (their ``param`` not empty: the degree-0 coefficients [N, 1, 3]
    and the ``rest_count`` others [N, rest_count, 3], flat), given to their Adam step instead."""
    if dc_step.param.shape[0] == 0:
        store_sh_gradient(grad_sh_out, grad_sh_rest_out, i, j, value)
    elif j == 0:
        for c in range(3):
            adam_step_value(dc_step, 3 * i + c, value[c])
    else:
        for c in range(3):
            adam_step_value(rest_step, 3 * (i * rest_count + j - 1) + c, value[c])


@wp.kernel
def sh_to_color_kernel(
    gauss_means: wp.array(dtype=wp.vec3),
    gauss_sh: wp.array2d(dtype=wp.vec3),
    gauss_sh_rest: wp.array2d(dtype=wp.vec3),
    sh_degree: int,
    camera_center: wp.vec3,
    camera_on_device: wp.array(dtype=Camera),
    radii: wp.array(dtype=wp.vec2i),
    colors_out: wp.array(dtype=wp.vec3),
    nonfinite_out: wp.array(dtype=wp.int32),
):
    """View-dependent colour max(SH . basis(dir) + 0.5, 0), dir from the camera centre to the mean (3DGS).

    ``gauss_sh`` [N, K] holds the coefficients; or pass the degree-0 ones there [N, 1] and the
    others in ``gauss_sh_rest`` [N, K - 1] (None: all in ``gauss_sh``).

    ``radii`` from the projection skips culled Gaussians (radius 0: colour 0, no gradient), which
    no pixel composites; pass None to colour every Gaussian. ``nonfinite_out`` (optional, None
    skips the check): ``nonfinite_out[0]`` is set to 1 when a coloured Gaussian's coefficients hold
    a NaN or an infinity (a non-finite term always makes the sum non-finite: NaN, inf - inf and
    0 * inf are NaN), so validating ``sh`` costs no read beyond the colouring's own.
    """
    i = wp.tid()
    center = camera_center  # or, with a non-empty camera_on_device, its entry 0's centre
    if camera_on_device.shape[0] > 0:
        center = camera_on_device[0].center
    if radii.shape[0] > 0:
        if radii[i][0] <= 0:
            colors_out[i] = wp.vec3(0.0, 0.0, 0.0)
            return
    color = SH_C0 * sh_coefficient(gauss_sh, gauss_sh_rest, i, 0)
    if sh_degree > 0:
        d = wp.normalize(gauss_means[i] - center)
        x = d[0]
        y = d[1]
        z = d[2]
        color = (
            color
            - SH_C1 * y * sh_coefficient(gauss_sh, gauss_sh_rest, i, 1)
            + SH_C1 * z * sh_coefficient(gauss_sh, gauss_sh_rest, i, 2)
            - SH_C1 * x * sh_coefficient(gauss_sh, gauss_sh_rest, i, 3)
        )
        if sh_degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            color = (
                color
                + SH_C2_0 * x * y * sh_coefficient(gauss_sh, gauss_sh_rest, i, 4)
                + SH_C2_1 * y * z * sh_coefficient(gauss_sh, gauss_sh_rest, i, 5)
                + SH_C2_2 * (2.0 * zz - xx - yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 6)
                + SH_C2_3 * x * z * sh_coefficient(gauss_sh, gauss_sh_rest, i, 7)
                + SH_C2_4 * (xx - yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 8)
            )
            if sh_degree > 2:
                color = (
                    color
                    + SH_C3_0 * y * (3.0 * xx - yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 9)
                    + SH_C3_1 * x * y * z * sh_coefficient(gauss_sh, gauss_sh_rest, i, 10)
                    + SH_C3_2 * y * (4.0 * zz - xx - yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 11)
                    + SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 12)
                    + SH_C3_4 * x * (4.0 * zz - xx - yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 13)
                    + SH_C3_5 * z * (xx - yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 14)
                    + SH_C3_6 * x * (xx - 3.0 * yy) * sh_coefficient(gauss_sh, gauss_sh_rest, i, 15)
                )
    color = color + wp.vec3(0.5, 0.5, 0.5)
    if nonfinite_out.shape[0] > 0:
        if not wp.isfinite(color):
            nonfinite_out[0] = 1  # every writer writes 1: no atomics needed
    colors_out[i] = wp.vec3(wp.max(color[0], 0.0), wp.max(color[1], 0.0), wp.max(color[2], 0.0))


# One float per SH coefficient of degree <= 3.
sh_vector = wp.types.vector(length=MAX_SH_COEFFICIENTS, dtype=wp.float32)
# The grouped SH adjoint runs one lane per coefficient in a group of lanes that shuffle together.
assert MAX_SH_COEFFICIENTS == GROUP_SIZE, "sh_to_color_grouped_backward_kernel needs one lane group per Gaussian"


@wp.func
def sh_basis(d: wp.vec3, degree: int):
    """The real SH basis functions of degree <= 3 (3DGS signs) at unit direction ``d``; 0 above ``degree``."""
    x = d[0]
    y = d[1]
    z = d[2]
    xx = x * x
    yy = y * y
    zz = z * z
    m1 = wp.where(degree > 0, 1.0, 0.0)
    m2 = wp.where(degree > 1, 1.0, 0.0)
    m3 = wp.where(degree > 2, 1.0, 0.0)
    return sh_vector(
        SH_C0,
        -m1 * SH_C1 * y,
        m1 * SH_C1 * z,
        -m1 * SH_C1 * x,
        m2 * SH_C2_0 * x * y,
        m2 * SH_C2_1 * y * z,
        m2 * SH_C2_2 * (2.0 * zz - xx - yy),
        m2 * SH_C2_3 * x * z,
        m2 * SH_C2_4 * (xx - yy),
        m3 * SH_C3_0 * y * (3.0 * xx - yy),
        m3 * SH_C3_1 * x * y * z,
        m3 * SH_C3_2 * y * (4.0 * zz - xx - yy),
        m3 * SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        m3 * SH_C3_4 * x * (4.0 * zz - xx - yy),
        m3 * SH_C3_5 * z * (xx - yy),
        m3 * SH_C3_6 * x * (xx - 3.0 * yy),
    )


@wp.func
def sh_basis_vjp(d: wp.vec3, w: sh_vector, degree: int):
    """sum_j w[j] * d(basis_j)/d(d), the basis differentiated in x, y, z as independent variables."""
    x = d[0]
    y = d[1]
    z = d[2]
    g = wp.vec3(-SH_C1 * w[3], -SH_C1 * w[1], SH_C1 * w[2])
    if degree > 1:
        # magnitudes; the signs of SH_C2 and SH_C3 are written into the expressions below
        c20 = SH_C2_0
        c22 = SH_C2_2
        c24 = SH_C2_4
        g += wp.vec3(
            c20 * (y * w[4] - z * w[7]) + 2.0 * x * (c24 * w[8] - c22 * w[6]),
            c20 * (x * w[4] - z * w[5]) - 2.0 * y * (c22 * w[6] + c24 * w[8]),
            -c20 * (y * w[5] + x * w[7]) + 4.0 * c22 * z * w[6],
        )
        if degree > 2:
            xx = x * x
            yy = y * y
            zz = z * z
            c30 = -SH_C3_0
            c31 = SH_C3_1
            c32 = -SH_C3_2
            c33 = SH_C3_3
            c35 = SH_C3_5
            g += wp.vec3(
                -6.0 * c30 * x * y * w[9]
                + c31 * y * z * w[10]
                + 2.0 * c32 * x * y * w[11]
                - 6.0 * c33 * x * z * w[12]
                - c32 * (4.0 * zz - 3.0 * xx - yy) * w[13]
                + 2.0 * c35 * x * z * w[14]
                - 3.0 * c30 * (xx - yy) * w[15],
                -3.0 * c30 * (xx - yy) * w[9]
                + c31 * x * z * w[10]
                - c32 * (4.0 * zz - xx - 3.0 * yy) * w[11]
                - 6.0 * c33 * y * z * w[12]
                + 2.0 * c32 * x * y * w[13]
                - 2.0 * c35 * y * z * w[14]
                + 6.0 * c30 * x * y * w[15],
                c31 * x * y * w[10]
                - 8.0 * c32 * y * z * w[11]
                + 3.0 * c33 * (2.0 * zz - xx - yy) * w[12]
                - 8.0 * c32 * x * z * w[13]
                + c35 * (xx - yy) * w[14],
            )
    return g


@wp.func
def sh_mean_gradient(v: wp.vec3, d: wp.vec3, w: sh_vector, degree: int):
    """The gradient of a Gaussian's mean through the view direction d = v / |v| of its colour, given
    ``w``, the colour gradient's dot product with each coefficient (0 at degree 0)."""
    if degree == 0:
        return wp.vec3(0.0, 0.0, 0.0)
    grad_d = sh_basis_vjp(d, w, degree)
    # d = v / |v|: the Jacobian is (I - d d^T) / |v|
    return (grad_d - d * wp.dot(d, grad_d)) / wp.length(v)


@wp.func
def clamp_gradient(color: wp.vec3, grad: wp.vec3):
    """The gradient through colour = max(raw, 0): it passes where the colour is positive (raw > 0)."""
    return wp.vec3(
        wp.where(color[0] > 0.0, grad[0], 0.0),
        wp.where(color[1] > 0.0, grad[1], 0.0),
        wp.where(color[2] > 0.0, grad[2], 0.0),
    )


@wp.kernel(enable_backward=False)
def sh_to_color_backward_kernel(
    gauss_means: wp.array(dtype=wp.vec3),
    gauss_sh: wp.array2d(dtype=wp.vec3),
    gauss_sh_rest: wp.array2d(dtype=wp.vec3),
    sh_degree: int,
    camera_center: wp.vec3,
    camera_on_device: wp.array(dtype=Camera),
    radii: wp.array(dtype=wp.vec2i),
    colors: wp.array(dtype=wp.vec3),
    grad_colors: wp.array(dtype=wp.vec3),
    dc_step: AdamStep,
    rest_step: AdamStep,
    grad_means_out: wp.array(dtype=wp.vec3),
    grad_sh_out: wp.array2d(dtype=wp.vec3),
    grad_sh_rest_out: wp.array2d(dtype=wp.vec3),
):
    """Adjoint of ``sh_to_color_kernel``, written out: each thread owns its Gaussian's gradients, so
    they are plain stores (every entry written, coefficients above the degree and culled Gaussians
    get 0), no atomics. ``colors`` is the forward output: colour = max(raw, 0) passes the gradient
    where it is positive. With ``dc_step`` and ``rest_step`` (not empty; ``gauss_sh`` [N, 1] and
    ``gauss_sh_rest`` given) the coefficients' gradients are not written: each thread applies the
    steps' Adam update to its Gaussian's coefficients with them, after reading them."""
    i = wp.tid()
    center = camera_center  # or, with a non-empty camera_on_device, its entry 0's centre
    if camera_on_device.shape[0] > 0:
        center = camera_on_device[0].center
    stored = sh_stored(gauss_sh, gauss_sh_rest)
    rest_count = gauss_sh_rest.shape[1]
    zero = wp.vec3(0.0, 0.0, 0.0)
    if radii.shape[0] > 0:
        if radii[i][0] <= 0:
            for j in range(stored):
                give_sh_gradient(grad_sh_out, grad_sh_rest_out, dc_step, rest_step, i, j, rest_count, zero)
            grad_means_out[i] = zero
            return
    v = gauss_means[i] - center
    d = wp.normalize(v)
    basis = sh_basis(d, sh_degree)
    count = (sh_degree + 1) * (sh_degree + 1)
    g = clamp_gradient(colors[i], grad_colors[i])
    # Loops over a constant count (16) are unrolled, so every vector index is a constant and the
    # vectors stay in registers (runtime bounds put them in local memory, three times slower).
    w = sh_vector()
    for j in range(MAX_SH_COEFFICIENTS):
        if j < count:
            w[j] = wp.dot(sh_coefficient(gauss_sh, gauss_sh_rest, i, j), g)  # before a step changes it
            give_sh_gradient(grad_sh_out, grad_sh_rest_out, dc_step, rest_step, i, j, rest_count, basis[j] * g)
        elif j < stored:
            give_sh_gradient(grad_sh_out, grad_sh_rest_out, dc_step, rest_step, i, j, rest_count, zero)
    for j in range(MAX_SH_COEFFICIENTS, stored):
        give_sh_gradient(grad_sh_out, grad_sh_rest_out, dc_step, rest_step, i, j, rest_count, zero)
    grad_means_out[i] = sh_mean_gradient(v, d, w, sh_degree)


# ------------------------------------------------------------------------------------------------
# The SH adjoint for CUDA, MAX_SH_COEFFICIENTS (16) threads per Gaussian: thread j of a Gaussian's
# half warp reads and writes its coefficient j, so a warp touches 384 contiguous bytes per access
# instead of 32 rows 192 bytes apart, and the half warp exchanges values in registers
# (``_lanes.group_read``). Launch with dim = MAX_SH_COEFFICIENTS * N. CUDA only (on the CPU the
# per-Gaussian kernel above runs). The forward pass, which only reads the coefficients, measured
# faster with one thread per Gaussian (the basis computed once, not 16 times).


@wp.func
def pick_sh(v: sh_vector, j: int):
    """``v[j]`` by 16 selects: indexing with a runtime ``j`` would put ``v`` in local memory."""
    r = v[0]
    for k in range(1, MAX_SH_COEFFICIENTS):
        r = wp.where(j == k, v[k], r)
    return r


@wp.kernel(enable_backward=False)
def sh_to_color_grouped_backward_kernel(
    gauss_means: wp.array(dtype=wp.vec3),
    gauss_sh: wp.array2d(dtype=wp.vec3),
    gauss_sh_rest: wp.array2d(dtype=wp.vec3),
    sh_degree: int,
    camera_center: wp.vec3,
    camera_on_device: wp.array(dtype=Camera),
    radii: wp.array(dtype=wp.vec2i),
    colors: wp.array(dtype=wp.vec3),
    grad_colors: wp.array(dtype=wp.vec3),
    dc_step: AdamStep,
    rest_step: AdamStep,
    grad_means_out: wp.array(dtype=wp.vec3),
    grad_sh_out: wp.array2d(dtype=wp.vec3),
    grad_sh_rest_out: wp.array2d(dtype=wp.vec3),
):
    """``sh_to_color_backward_kernel`` with one thread per coefficient (dim MAX_SH_COEFFICIENTS * N = 16 N, CUDA
    only). With the steps, a coefficient's thread reads it before it gives the step its gradient."""
    t = wp.tid()
    center = camera_center  # or, with a non-empty camera_on_device, its entry 0's centre
    if camera_on_device.shape[0] > 0:
        center = camera_on_device[0].center
    i = t // MAX_SH_COEFFICIENTS
    j = t - i * MAX_SH_COEFFICIENTS
    stored = sh_stored(gauss_sh, gauss_sh_rest)
    rest_count = gauss_sh_rest.shape[1]
    zero = wp.vec3(0.0, 0.0, 0.0)
    if radii.shape[0] > 0:
        if radii[i][0] <= 0:  # the whole half warp leaves together
            for k in range(j, stored, MAX_SH_COEFFICIENTS):
                give_sh_gradient(grad_sh_out, grad_sh_rest_out, dc_step, rest_step, i, k, rest_count, zero)
            if j == 0:
                grad_means_out[i] = zero
            return
    count = (sh_degree + 1) * (sh_degree + 1)
    v = gauss_means[i] - center
    d = wp.normalize(v)
    b = pick_sh(sh_basis(d, sh_degree), j)
    coefficient = zero
    if j < count:
        coefficient = sh_coefficient(gauss_sh, gauss_sh_rest, i, j)
    g = clamp_gradient(colors[i], grad_colors[i])
    if j < stored:
        give_sh_gradient(
            grad_sh_out, grad_sh_rest_out, dc_step, rest_step, i, j, rest_count, wp.where(j < count, b * g, zero)
        )
    for k in range(j + MAX_SH_COEFFICIENTS, stored, MAX_SH_COEFFICIENTS):
        give_sh_gradient(grad_sh_out, grad_sh_rest_out, dc_step, rest_step, i, k, rest_count, zero)
    # every lane gathers the group's weights dot(coefficient, g); lane 0 writes the mean's gradient
    w_j = wp.dot(coefficient, g)
    w = sh_vector()
    for k in range(MAX_SH_COEFFICIENTS):
        w[k] = group_read(w_j, k)
    if j == 0:
        grad_means_out[i] = sh_mean_gradient(v, d, w, sh_degree)


# ------------------------------------------------------------------------------------------------
# The SH adjoint for CUDA with the coefficients staged in shared memory, one thread per Gaussian:
# a block of SH_BLOCK threads copies its Gaussians' higher coefficients (``gauss_sh_rest``, read
# as flat floats) into shared memory with coalesced loads, each thread then computes its Gaussian's
# basis once and swaps its coefficients for their gradients in place, and the block copies the
# gradients out with coalesced stores. The grouped kernel above computes every Gaussian's basis and
# shuffles 16 times, once per coefficient thread: it is bound by instructions, not by memory.
# Launch with dim = N rounded up to a multiple of SH_BLOCK and block_dim = SH_BLOCK (every thread
# reaches the block's barriers). CUDA only, two arrays only (``gauss_sh`` [N, 1], ``gauss_sh_rest``
# [N, K - 1], K <= MAX_SH_COEFFICIENTS).

SH_BLOCK = 128
SH_STAGE_FLOATS = SH_BLOCK * 3 * (MAX_SH_COEFFICIENTS - 1)  # 22.5 KiB of shared memory a block
SH_STAGE_STORE = wp.constant(0)
SH_STAGE_LOAD = wp.constant(1)


@wp.func_native(
    f"""
#if defined(__CUDA_ARCH__)
    __shared__ float stage[{SH_STAGE_FLOATS}];
    if (op == {SH_STAGE_STORE}) {{ stage[index] = value; return value; }}
    return stage[index];
#else
    return value;
#endif
"""
)
def sh_stage(op: int, index: int, value: float) -> float:
    """The block's shared float array (CUDA only): SH_STAGE_STORE ``value`` at ``index`` (returns
    it) or SH_STAGE_LOAD ``index``. A Gaussian's floats start at its lane times the floats a
    Gaussian stores, an odd stride for degree 3 (45): the lanes of a warp hit distinct banks."""
    ...


@wp.func
def sh_stage_vec3(slot: int):
    return wp.vec3(
        sh_stage(SH_STAGE_LOAD, slot, 0.0),
        sh_stage(SH_STAGE_LOAD, slot + 1, 0.0),
        sh_stage(SH_STAGE_LOAD, slot + 2, 0.0),
    )


@wp.func
def sh_stage_store_vec3(slot: int, value: wp.vec3):
    sh_stage(SH_STAGE_STORE, slot, value[0])
    sh_stage(SH_STAGE_STORE, slot + 1, value[1])
    sh_stage(SH_STAGE_STORE, slot + 2, value[2])


@wp.kernel(enable_backward=False)
def sh_to_color_staged_backward_kernel(
    gauss_means: wp.array(dtype=wp.vec3),
    gauss_sh: wp.array2d(dtype=wp.vec3),
    gauss_sh_rest: wp.array(dtype=float),
    sh_degree: int,
    camera_center: wp.vec3,
    camera_on_device: wp.array(dtype=Camera),
    radii: wp.array(dtype=wp.vec2i),
    colors: wp.array(dtype=wp.vec3),
    grad_colors: wp.array(dtype=wp.vec3),
    dc_step: AdamStep,
    rest_step: AdamStep,
    grad_means_out: wp.array(dtype=wp.vec3),
    grad_sh_out: wp.array2d(dtype=wp.vec3),
    grad_sh_rest_out: wp.array(dtype=float),
):
    """``sh_to_color_backward_kernel`` with ``gauss_sh_rest`` and its gradient as flat float arrays
    (N * 3 * (K - 1)), staged in shared memory, CUDA only. Launch with dim N rounded up to a
    multiple of SH_BLOCK and block_dim exactly SH_BLOCK: a thread's slot is its id modulo SH_BLOCK,
    so a larger block would put two threads on one slot. With ``dc_step`` and ``rest_step`` (not
    empty) the coefficients' gradients are not written: the thread of a Gaussian applies the Adam
    step to its degree-0 coefficients, and the block's copy-out applies it to the others, which the
    block alone reads and writes (read before: the copy-in), coalesced."""
    t = wp.tid()
    center = camera_center  # or, with a non-empty camera_on_device, its entry 0's centre
    if camera_on_device.shape[0] > 0:
        center = camera_on_device[0].center
    lane = t % SH_BLOCK
    n = gauss_means.shape[0]
    row = gauss_sh_rest.shape[0] // wp.max(n, 1)  # floats per Gaussian: 3 (K - 1)
    start = (t - lane) * row
    end = wp.min(n * row, start + SH_BLOCK * row)
    stepped = dc_step.param.shape[0] > 0
    for k in range(start + lane, end, SH_BLOCK):  # the block's rows, coalesced
        sh_stage(SH_STAGE_STORE, k - start, gauss_sh_rest[k])
    block_sync()
    if t < n:
        zero = wp.vec3(0.0, 0.0, 0.0)
        own = lane * row
        stored = 1 + row // 3
        culled = int(0)
        if radii.shape[0] > 0:
            if radii[t][0] <= 0:
                culled = 1
        grad_dc = zero
        if culled == 1:
            for k in range(row):
                sh_stage(SH_STAGE_STORE, own + k, 0.0)
            grad_means_out[t] = zero
        else:
            v = gauss_means[t] - center
            d = wp.normalize(v)
            basis = sh_basis(d, sh_degree)
            count = (sh_degree + 1) * (sh_degree + 1)
            g = clamp_gradient(colors[t], grad_colors[t])
            w = sh_vector()
            grad_dc = basis[0] * g
            w[0] = wp.dot(gauss_sh[t, 0], g)
            # A constant count (16): unrolled, every vector index a constant (registers, not local memory).
            for j in range(1, MAX_SH_COEFFICIENTS):
                if j < stored:
                    slot = own + 3 * (j - 1)
                    if j < count:
                        w[j] = wp.dot(sh_stage_vec3(slot), g)
                        sh_stage_store_vec3(slot, basis[j] * g)
                    else:
                        sh_stage_store_vec3(slot, zero)
            grad_means_out[t] = sh_mean_gradient(v, d, w, sh_degree)
        if stepped:  # after w[0] read the coefficient
            if adam_step_halted(dc_step) == 0:
                dc_rates = adam_step_rates(dc_step)
                for c in range(3):
                    adam_step_with(dc_step, dc_rates, 3 * t + c, grad_dc[c])
        else:
            grad_sh_out[t, 0] = grad_dc
    block_sync()
    if not stepped:
        for k in range(start + lane, end, SH_BLOCK):
            grad_sh_rest_out[k] = sh_stage(SH_STAGE_LOAD, k - start, 0.0)
    elif adam_step_halted(rest_step) == 0:
        rates = adam_step_rates(rest_step)  # once a thread, not once a value
        for k in range(start + lane, end, SH_BLOCK):
            adam_step_with(rest_step, rates, k, sh_stage(SH_STAGE_LOAD, k - start, 0.0))
    block_sync()  # a capped grid runs a block again: its next copy-in must wait for this copy-out
