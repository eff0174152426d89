"""Cameras: viser's (wxyz, position, vertical fov, aspect) and cdcgs's (world-to-camera viewmat, K).

Both use the OpenCV convention (x right, y down, z forward); viser's ``wxyz`` and ``position`` are
the camera-to-world rotation and the camera centre.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..geometry import quat_to_rotation

__all__ = ["camera_rotation", "matrix_to_quat", "pinhole_to_viser", "viser_to_pinhole"]


def camera_rotation(wxyz) -> np.ndarray:
    """[3, 3] float64 rotation of a (w, x, y, z) quaternion given as any sequence (normalised)."""
    return quat_to_rotation(torch.as_tensor(np.asarray(wxyz, dtype=np.float64))).numpy()


def matrix_to_quat(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a [3, 3] rotation, w >= 0 (Shepperd's method, stable for any angle)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > max(m[0, 0], m[1, 1], m[2, 2]):
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax([m[0, 0], m[1, 1], m[2, 2]]))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def viser_to_pinhole(
    wxyz, position, fov: float, aspect: float, height: int
) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """(viewmat [4, 4], K [3, 3], width, height) of a viser camera rendered ``height`` pixels high.

    ``fov`` is vertical, in radians; ``aspect`` is width / height. Square pixels, principal point
    at the image centre.
    """
    width = max(1, round(height * aspect))
    rotation = camera_rotation(wxyz)
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3] = -rotation.T @ np.asarray(position, dtype=np.float64)
    focal = 0.5 * height / math.tan(0.5 * fov)
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return torch.from_numpy(viewmat).float(), torch.from_numpy(K).float(), width, height


def pinhole_to_viser(viewmat, K, height: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(wxyz, position, vertical fov in radians) of a world-to-camera ``viewmat`` and intrinsics."""
    viewmat = torch.as_tensor(viewmat).double().numpy()
    rotation = viewmat[:3, :3].T
    position = -rotation @ viewmat[:3, 3]
    fy = float(torch.as_tensor(K)[1, 1])
    return matrix_to_quat(rotation), position, 2.0 * math.atan(0.5 * height / fy)
