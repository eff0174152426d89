"""Rotations as torch code: the one quaternion-to-matrix conversion outside the kernels, and the
similarity that best maps one set of points onto another (to compare two sets of camera poses).

Quaternions are (w, x, y, z), as everywhere in cdcgs; the Warp kernels have their own conversion
(``quat_to_rotation`` in cdcgs/kernels/projection.py), which tests compare with this one.
"""

from __future__ import annotations

import torch

__all__ = ["quat_to_rotation", "similarity_transform"]


def quat_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation matrices of quaternions [..., 4] (w, x, y, z), normalised first."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def similarity_transform(source: torch.Tensor, target: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
    """(s, R, t) minimising the sum of |s R source_k + t - target_k|^2 over points as rows [K, 3]
    (Umeyama 1991), in float64; R is a rotation (no reflection). Used to compare camera centres of
    two reconstructions of one scene, which agree at best up to such a similarity."""
    if source.shape != target.shape or source.dim() != 2 or source.shape[1] != 3 or source.shape[0] < 3:
        raise ValueError(
            f"similarity_transform needs two [K, 3] point sets with K >= 3, got {list(source.shape)} "
            f"and {list(target.shape)}"
        )
    a, b = source.double(), target.double()
    mean_a, mean_b = a.mean(0), b.mean(0)
    a, b = a - mean_a, b - mean_b
    spread = torch.linalg.svdvals(a)
    if spread[1] <= 1e-9 * max(float(spread[0]), 1e-300):
        raise ValueError("similarity_transform: the source points coincide or lie on one line (no unique rotation)")
    u, d, vt = torch.linalg.svd(b.T @ a / len(a))
    sign = torch.ones(3, dtype=torch.float64, device=a.device)
    if torch.det(u) * torch.det(vt) < 0:
        sign[-1] = -1.0
    rotation = u @ torch.diag(sign) @ vt
    scale = float((d * sign).sum() / a.pow(2).sum(1).mean())
    return scale, rotation, mean_b - scale * rotation @ mean_a
