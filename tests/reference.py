"""An independent, dense, pure-torch float64 Gaussian splatting renderer, used only by tests.

Every pixel against every Gaussian, sorted by depth, no tiles. It follows the same conventions
as cdcgs (COLMAP camera, pixel centres at +0.5, 3DGS SH basis, 0.3 px^2 dilation, alpha clamp
0.99, 1/255 threshold, stop below transmittance 1e-4), written from the formulas, not from the
kernels. Gradients come from torch autograd.
"""

import math

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """[N, (degree+1)^2] real SH basis values of unit directions [N, 3] (3DGS sign convention)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, -1)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    rows = [entry for row in rows for entry in row]
    return torch.stack(rows, -1).reshape(*q.shape[:-1], 3, 3)


def project(means, quats, scales, opacities, viewmat, K, width, height, antialiased=False, near=0.01):
    """Per-Gaussian screen quantities in float64: mean2d, conic matrix, depths, opacity, valid mask."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    z = p[:, 2]
    rot = quat_to_matrix(quats)
    m = rot * scales[:, None, :]
    cov_cam = R @ (m @ m.transpose(1, 2)) @ R.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    zs = torch.where(z > near, z, torch.ones_like(z))  # keep the math finite for culled ones
    u = torch.clamp(p[:, 0] / zs, -1.3 * cx / fx, 1.3 * (width - cx) / fx) * zs
    v = torch.clamp(p[:, 1] / zs, -1.3 * cy / fy, 1.3 * (height - cy) / fy) * zs
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [torch.stack([fx / zs, zero, -fx * u / zs**2], -1), torch.stack([zero, fy / zs, -fy * v / zs**2], -1)], -2
    )
    cov2d = J @ cov_cam @ J.transpose(1, 2)
    det_raw = torch.linalg.det(cov2d)
    cov2d = cov2d + 0.3 * torch.eye(2, dtype=cov2d.dtype)
    det = torch.linalg.det(cov2d)
    opac = opacities
    if antialiased:
        opac = opac * torch.sqrt(torch.clamp(det_raw / det, min=0.0))
    conic = torch.linalg.inv(cov2d)
    mean2d = torch.stack([fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy], -1)
    valid = (z > near) & (det > 0)
    return mean2d, conic, z, opac, valid


def sh_colors(means, sh, degree, viewmat):
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    center = -R.T @ t
    dirs = means - center
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    basis = sh_basis(dirs, degree)
    k = (degree + 1) ** 2
    return torch.clamp((basis[:, :k, None] * sh[:, :k]).sum(1) + 0.5, min=0.0)


def render(
    means,
    quats,
    scales,
    opacities,
    sh=None,
    *,
    viewmat,
    K,
    width,
    height,
    sh_degree=None,
    colors=None,
    background=None,
    antialiased=False,
    near=0.01,
):
    """Dense float64 render: image [H, W, 3], alpha [H, W], expected depth [H, W], weights [H*W, N].

    The weights are those of each pixel (row-major) for each Gaussian, 0 where it is not composited.
    """
    if colors is None:
        if sh_degree is None:
            sh_degree = math.isqrt(sh.shape[1]) - 1
        colors = sh_colors(means, sh, sh_degree, viewmat)
    if background is None:
        background = torch.zeros(3, dtype=means.dtype)
    mean2d, conic, depths, opac, valid = project(
        means, quats, scales, opacities, viewmat, K, width, height, antialiased, near
    )
    order = torch.sort(depths.detach(), stable=True).indices
    order = order[valid[order]]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means.dtype), torch.arange(width, dtype=means.dtype), indexing="ij"
    )
    pix = torch.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], -1)  # [P, 2]
    d = mean2d[order][None] - pix[:, None]  # [P, M, 2]
    Q = conic[order]
    power = -0.5 * torch.einsum("pmi,mij,pmj->pm", d, Q, d)
    alpha = torch.clamp(opac[order][None] * torch.exp(power), max=0.99)
    alpha = torch.where(alpha >= 1.0 / 255.0, alpha, torch.zeros_like(alpha))
    trans_after = torch.cumprod(1 - alpha, dim=1)
    # Composite front to back until a Gaussian would take transmittance below 1e-4; it and all
    # behind it are dropped. trans_after is non-increasing, so that is simply trans_after >= 1e-4.
    keep = (trans_after.detach() >= 1e-4).to(alpha.dtype)
    alpha = alpha * keep
    trans_after = torch.cumprod(1 - alpha, dim=1)
    trans_before = torch.cat([torch.ones_like(trans_after[:, :1]), trans_after[:, :-1]], 1)
    weights = alpha * trans_before  # [P, M]
    final_t = trans_after[:, -1] if trans_after.shape[1] else torch.ones(pix.shape[0], dtype=means.dtype)
    image = weights @ colors[order] + final_t[:, None] * background
    acc = 1 - final_t
    depth_sum = weights @ depths[order]
    exp_depth = torch.where(acc > 0, depth_sum / acc.clamp_min(1e-10), torch.zeros_like(acc))
    full_weights = torch.zeros(pix.shape[0], means.shape[0], dtype=means.dtype)
    full_weights[:, order] = weights.detach()
    return (
        image.reshape(height, width, 3),
        acc.reshape(height, width),
        exp_depth.reshape(height, width),
        full_weights,
    )
