"""Nearest neighbours of Gaussian centres from torch: exact KNN, initial scales, CDC-GS density."""

from __future__ import annotations

import torch
import warp as wp

from ._interop import torch_allocators, warp_scope, wp_array
from .kernels.knn import MAX_K, knn_search

__all__ = ["density", "initial_scales", "knn"]


def knn(points: torch.Tensor, k: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact k nearest other points of every point, on the points' device.

    Args:
        points: [N, 3] float32 on any device.
        k: neighbours per point, 1..16 and less than N.

    Returns:
        sqdist [N, k] float32 squared distances and index [N, k] int64, ascending by distance,
        ties by the smaller index. Identical points are at distance 0.

    Raises:
        ValueError: ``points`` of the wrong type, dtype or shape, empty, with NaN or infinite
            coordinates, or ``k`` out of range.
    """
    if not isinstance(points, torch.Tensor):
        raise ValueError(f"points must be a torch.Tensor, got {type(points).__name__}")
    if points.dtype != torch.float32:
        raise ValueError(f"points must be float32, got {points.dtype}")
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape [N, 3], got {list(points.shape)}")
    points = points.detach().contiguous()
    n = points.shape[0]
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= MAX_K:
        raise ValueError(f"k must be an int in 1..{MAX_K}, got {k!r}")
    sqdist = torch.empty(n, k, dtype=torch.float32, device=points.device)
    index = torch.empty(n, k, dtype=torch.int32, device=points.device)
    with warp_scope(points.device):
        knn_search(
            wp_array(points, wp.vec3),
            k,
            sqdist_out=wp_array(sqdist, wp.float32),
            index_out=wp_array(index, wp.int32),
            allocate=torch_allocators(points.device)[0],
        )
    return sqdist, index.long()


def _geometric_mean(sqdist: torch.Tensor) -> torch.Tensor:
    # In float64 through logs: a product of three tiny squared distances underflows float32.
    return sqdist.double().log().mean(dim=-1).exp()


def initial_scales(points: torch.Tensor, rule: str = "3dgs", k: int = 3) -> torch.Tensor:
    """[N] initial scale (same on all three axes) of a Gaussian at each point.

    rule "3dgs": sqrt of the mean of the squared distances to the k nearest points, with the
    mean floored at 1e-7 (as 3DGS). rule "cdc": sqrt of their geometric mean, floored at 1e-7
    likewise (the CDC-GS code; section 3 of the paper).
    """
    sqdist, _ = knn(points, k)
    if rule == "3dgs":
        return sqdist.mean(dim=-1).clamp_min(1e-7).sqrt()
    if rule == "cdc":
        return _geometric_mean(sqdist).clamp_min(1e-7).sqrt().float()
    raise ValueError(f"rule must be '3dgs' or 'cdc', got {rule!r}")


def density(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """[N] CDC-GS density 1 / (d + 1e-6), d the geometric mean of the squared distances to the k
    nearest, floored at 1e-7 as the CDC-GS code (so at most 1 / 1.1e-6, about 9.1e5)."""
    sqdist, _ = knn(points, k)
    return (1.0 / (_geometric_mean(sqdist).clamp_min(1e-7) + 1e-6)).float()
