"""Photometric loss and metrics on [H, W, 3] images in [0, 1].

Two implementations of the 3DGS loss (1 - w) L1 + w (1 - SSIM): :func:`photometric_loss`, kornia's
SSIM and torch's L1 (the reference, about sixty torch kernels forward and backward), and
:func:`fused_photometric_loss`, the same loss as two Warp kernels forward and two backward
(cdcgs.kernels.loss: separable passes over the window), which also returns the mean squared error
for the PSNR. The training uses the fused one unless ``--no-fused-loss``.
"""

import functools

import kornia
import torch
import warp as wp

from .._interop import launch, warp_scope, wp_arg
from ..kernels.loss import (
    ROW_GATHERS,
    ROW_MOMENTS,
    SSIM_RADIUS,
    ssim_l1_backward_kernel,
    ssim_l1_backward_rows_kernel,
    ssim_l1_forward_kernel,
    ssim_l1_forward_rows_kernel,
    ssim_l1_launch_size,
)

__all__ = ["fused_photometric_loss", "mse_to_psnr", "photometric_loss", "psnr", "ssim"]


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM with kornia's 11 px Gaussian window (sigma 1.5)."""
    return kornia.metrics.ssim(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], window_size=11).mean()


def psnr(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    mse = ((image.clamp(0, 1) - target) ** 2).mean()
    return mse_to_psnr(mse)


def mse_to_psnr(mse: torch.Tensor) -> torch.Tensor:
    return -10.0 * torch.log10(mse.clamp_min(1e-12))


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM), the 3DGS loss (w = 0.2)."""
    l1 = (image - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim(image, target))


_TARGET_TYPES = {torch.uint8: wp.uint8, torch.float32: wp.float32}


@functools.cache
def _kernels(target_dtype):
    """The overloads for this target type: forward rows, forward, backward (the backward's rows
    pass reads no target). Made once per type: ``wp.overload`` parses the signature again on
    every call (about 0.2 ms of host time per training step on a 2-core CPU, twice a step)."""
    spec = {"target": wp.array3d(dtype=target_dtype)}
    return tuple(
        wp.overload(kernel, spec)
        for kernel in (ssim_l1_forward_rows_kernel, ssim_l1_forward_kernel, ssim_l1_backward_kernel)
    )


class _FusedLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image, target, ssim_weight: float):
        height, width = image.shape[:2]
        target_type = _TARGET_TYPES[target.dtype]
        rows_kernel, forward_kernel, _ = _kernels(target_type)
        # The horizontal pass's moments and the three derivative maps of SSIM that the backward
        # gathers; a pure L1 reads neither, and its arguments are one pixel each.
        size = (height, width) if ssim_weight else (1, 1)
        row_moments = image.new_empty(ROW_MOMENTS, *size, 3)
        maps = image.new_empty(3, *size, 3)
        sums = image.new_zeros(2)  # loss, mean squared error of the clamped image
        inv_count = 1.0 / (3 * height * width)
        image_arg, target_arg = wp_arg(image, wp.vec3), wp_arg(target, target_type)
        with warp_scope(image.device):
            if ssim_weight:
                launch(
                    rows_kernel, height * width, inputs=[image_arg, target_arg], outputs=[wp_arg(row_moments, wp.vec3)]
                )
            launch(
                forward_kernel,
                ssim_l1_launch_size(height, width),
                inputs=[image_arg, target_arg, float(ssim_weight), inv_count, wp_arg(row_moments, wp.vec3)],
                outputs=[wp_arg(sums, wp.float32), *(wp_arg(m, wp.vec3) for m in maps)],
            )
        ctx.save_for_backward(image, target, maps)
        ctx.ssim_weight = float(ssim_weight)
        loss, mse = sums.unbind()
        ctx.mark_non_differentiable(mse)
        return loss, mse

    @staticmethod
    def backward(ctx, grad_loss, _grad_mse):
        image, target, maps = ctx.saved_tensors
        height, width = image.shape[:2]
        target_type = _TARGET_TYPES[target.dtype]
        _, _, backward_kernel = _kernels(target_type)
        # A new scratch array rather than keeping the forward's row_moments ([5, H, W]) allocated
        # until here; torch's caching allocator makes this one cheap.
        row_gathers = image.new_empty(ROW_GATHERS, *maps.shape[1:])
        grad_image = torch.empty_like(image)
        grad_loss = grad_loss.reshape(1).float().contiguous()  # read on the device: no host synchronisation
        with warp_scope(image.device):
            if ctx.ssim_weight:
                launch(
                    ssim_l1_backward_rows_kernel,
                    height * width,
                    inputs=[wp_arg(m, wp.vec3) for m in maps],
                    outputs=[wp_arg(row_gathers, wp.vec3)],
                )
            launch(
                backward_kernel,
                height * width,
                inputs=[
                    wp_arg(image, wp.vec3),
                    wp_arg(target, target_type),
                    ctx.ssim_weight,
                    1.0 / (3 * height * width),
                    wp_arg(grad_loss, wp.float32),
                    wp_arg(row_gathers, wp.vec3),
                ],
                outputs=[wp_arg(grad_image, wp.vec3)],
            )
        return grad_image, None, None


def fused_photometric_loss(
    image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2
) -> tuple[torch.Tensor, torch.Tensor]:
    """(1 - w) L1 + w (1 - SSIM) as :func:`photometric_loss` computes it, in two Warp kernels
    forward and two backward, and the mean squared error of ``image.clamp(0, 1)`` against the
    target (for :func:`mse_to_psnr`; not differentiable).

    Args:
        image: [H, W, 3] float32, the render (differentiable), H and W at least 6.
        target: [H, W, 3] on the same device, uint8 (read as value / 255, as photos are kept) or
            float32 in [0, 1]. Not differentiated.
        ssim_weight: w in [0, 1].
    """
    if not isinstance(image, torch.Tensor) or image.dtype != torch.float32 or image.dim() != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be a float32 [H, W, 3] tensor, got {_describe(image)}")
    if not isinstance(target, torch.Tensor) or target.dtype not in _TARGET_TYPES or target.shape != image.shape:
        raise ValueError(
            f"target must be a uint8 or float32 tensor of the image's shape {list(image.shape)}, got {_describe(target)}"
        )
    if target.device != image.device:
        raise ValueError(f"target is on {target.device} but the image is on {image.device}")
    if min(image.shape[:2]) <= SSIM_RADIUS:
        raise ValueError(f"images must be larger than {SSIM_RADIUS} pixels on each side, got {list(image.shape[:2])}")
    if not 0.0 <= ssim_weight <= 1.0:
        raise ValueError(f"ssim_weight must be in [0, 1], got {ssim_weight}")
    return _FusedLoss.apply(image.contiguous(), target.detach().contiguous(), float(ssim_weight))


def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"{value.dtype} {list(value.shape)}"
    return type(value).__name__
