"""Held-out evaluation: PSNR, SSIM, LPIPS (when its weights load), render speed, and the pictures."""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from ..render import prepare_camera, rasterize
from .loss import psnr, ssim
from .outputs import view_stem

__all__ = ["error_triptych", "evaluate", "lpips_metric", "render_view"]


def lpips_metric(device: torch.device):
    """(callable, None) computing LPIPS (VGG) of [B, 3, H, W] images in [0, 1], or (None, reason)
    when it is unavailable. Build it once per run and pass it to :func:`evaluate`.

    LPIPS needs pretrained network weights; where they cannot be loaded (no ``lpips`` package, no
    network to fetch them), it is reported as unavailable, never estimated.
    """
    try:
        import lpips

        net = lpips.LPIPS(net="vgg", verbose=False).to(device).eval()
        return (lambda a, b: net(a * 2 - 1, b * 2 - 1).flatten()), None
    except Exception as err:  # missing package or weights that cannot be downloaded
        return None, f"unavailable: {type(err).__name__}: {str(err)[:160]}"


def render_view(model, view, background: torch.Tensor, antialiased: bool = False, camera=None):
    """(image, alpha, info) of ``model`` seen from ``view`` (``camera``: its PreparedCamera, if
    the caller keeps one)."""
    if camera is None:
        camera = prepare_camera(view.viewmat, view.K, view.width, view.height)
    return rasterize(**model.render_args(), camera=camera, background=background, antialiased=antialiased)


def error_triptych(gt: torch.Tensor, image: torch.Tensor) -> np.ndarray:
    """[H, 3W, 3] uint8: ground truth | render | error map (mean absolute error x 4, 'hot'-like)."""
    error = (image - gt).abs().mean(-1).mul(4).clamp(0, 1)
    heat = torch.stack([(error * 3).clamp(0, 1), (error * 3 - 1).clamp(0, 1), (error * 3 - 2).clamp(0, 1)], -1)
    strip = torch.cat([gt, image.clamp(0, 1), heat], dim=1)
    return (strip.detach().cpu().numpy() * 255 + 0.5).astype(np.uint8)


@torch.no_grad()
def evaluate(
    model,
    views,
    *,
    background: torch.Tensor,
    antialiased: bool = False,
    save_dir: str | None = None,
    render=None,
    lpips: tuple | None = None,
) -> dict:
    """Metrics over ``views`` (means over views) and, with ``save_dir``, one triptych PNG per view.

    ``render(model, view, background, antialiased) -> (image, alpha, info)`` draws a view (cdcgs's
    rasterizer by default, each view's camera prepared once; the benchmarks pass a peer's to score
    it the same way). ``lpips``: what :func:`lpips_metric` returned (built here when not given).
    """
    if not views:
        return {"views": 0}
    if render is None:
        cameras = {id(view): prepare_camera(view.viewmat, view.K, view.width, view.height) for view in views}

        def render(model, view, background, antialiased):
            return render_view(model, view, background, antialiased, camera=cameras[id(view)])

    device = model.device
    lpips_fn, lpips_reason = lpips if lpips is not None else lpips_metric(device)
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

            Image.fromarray(error_triptych(gt, image)).save(os.path.join(save_dir, f"{view_stem(view.name)}.png"))
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
