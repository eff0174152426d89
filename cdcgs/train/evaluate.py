"""Held-out evaluation: PSNR, SSIM, LPIPS (when its weights load), render speed, and the pictures."""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from ..render import rasterize
from .loss import psnr, ssim

_LPIPS: dict = {}


def lpips_metric(device: torch.device):
    """An LPIPS (VGG) callable on [B, 3, H, W] images in [0, 1], or (None, reason) when unavailable.

    LPIPS needs pretrained network weights; where they cannot be loaded (no ``lpips`` package, no
    network to fetch them), it is reported as unavailable, never estimated.
    """
    key = str(device)
    if key not in _LPIPS:
        try:
            import lpips

            net = lpips.LPIPS(net="vgg", verbose=False).to(device).eval()
            _LPIPS[key] = (lambda a, b: net(a * 2 - 1, b * 2 - 1).flatten(), None)
        except Exception as err:  # missing package or weights that cannot be downloaded
            _LPIPS[key] = (None, f"unavailable: {type(err).__name__}: {str(err)[:160]}")
    return _LPIPS[key]


def render_view(model, view, background: torch.Tensor, antialiased: bool = False):
    return rasterize(
        **model.render_args(), viewmat=view.viewmat, K=view.K, width=view.width, height=view.height,
        background=background, antialiased=antialiased,
    )  # fmt: skip


def error_triptych(gt: torch.Tensor, image: torch.Tensor) -> np.ndarray:
    """[H, 3W, 3] uint8: ground truth | render | error map (mean absolute error x 4, 'hot'-like)."""
    error = (image - gt).abs().mean(-1).mul(4).clamp(0, 1)
    heat = torch.stack([(error * 3).clamp(0, 1), (error * 3 - 1).clamp(0, 1), (error * 3 - 2).clamp(0, 1)], -1)
    strip = torch.cat([gt, image.clamp(0, 1), heat], dim=1)
    return (strip.detach().cpu().numpy() * 255 + 0.5).astype(np.uint8)


@torch.no_grad()
def evaluate(
    model, views, *, background: torch.Tensor, antialiased: bool = False, save_dir: str | None = None, render=render_view
) -> dict:
    """Metrics over ``views`` (means over views) and, with ``save_dir``, one triptych PNG per view.

    ``render(model, view, background, antialiased) -> (image, alpha, info)`` draws a view (cdcgs's
    rasterizer by default; the benchmarks pass a peer's to score it the same way).
    """
    if not views:
        return {"views": 0}
    device = model.device
    lpips_fn, lpips_reason = lpips_metric(device)
    per_view = []
    if save_dir:
        os.makedirs(save_dir, exist_ok=True)
    for view in views:
        image, _, _ = render(model, view, background, antialiased)
        gt = view.image.to(device).float() / 255.0
        entry = {"name": view.name, "psnr": psnr(image, gt).item(), "ssim": ssim(image, gt).item()}
        if lpips_fn is not None:
            entry["lpips"] = lpips_fn(image.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]).item()
        per_view.append(entry)
        if save_dir:
            from PIL import Image

            stem = os.path.splitext(view.name.replace(os.sep, "_"))[0]
            Image.fromarray(error_triptych(gt, image)).save(os.path.join(save_dir, f"{stem}.png"))
    # Render speed: every view once more, timed after the first pass warmed everything up.
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    for view in views:
        render(model, view, background, antialiased)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - start
    metrics = {
        "views": len(views),
        "psnr": float(np.mean([v["psnr"] for v in per_view])),
        "ssim": float(np.mean([v["ssim"] for v in per_view])),
        "lpips": float(np.mean([v["lpips"] for v in per_view])) if lpips_fn is not None else None,
        "render_fps": len(views) / max(seconds, 1e-9),
        "num_gaussians": model.num,
        "per_view": per_view,
    }
    if lpips_fn is None:
        metrics["lpips_note"] = lpips_reason
    return metrics
