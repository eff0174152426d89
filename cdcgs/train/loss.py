"""Photometric loss and metrics on [H, W, 3] images in [0, 1]."""

import kornia
import torch

__all__ = ["photometric_loss", "psnr", "ssim"]


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM with kornia's 11 px Gaussian window (sigma 1.5)."""
    return kornia.metrics.ssim(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], window_size=11).mean()


def psnr(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    mse = ((image.clamp(0, 1) - target) ** 2).mean()
    return -10.0 * torch.log10(mse.clamp_min(1e-12))


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM), the 3DGS loss (w = 0.2)."""
    l1 = (image - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim(image, target))
