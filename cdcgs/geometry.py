"""Rotations as torch code: the one quaternion-to-matrix conversion outside the kernels.

Quaternions are (w, x, y, z), as everywhere in cdcgs; the Warp kernels have their own conversion
(``quat_to_rotation`` in cdcgs/kernels/projection.py), which tests compare with this one.
"""

from __future__ import annotations

import torch

__all__ = ["quat_to_rotation"]


def quat_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] rotation matrices of quaternions [..., 4] (w, x, y, z), normalised first."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(row, -1) for row in rows], -2)
