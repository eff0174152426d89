"""Held-out evaluation: PSNR, SSIM, LPIPS-VGG and LPIPS-Alex (when their weights load), render
speed, and the pictures."""

from __future__ import annotations

import io
import os
import time

import numpy as np
import torch

from ..errors import InputError
from ..lpips.network import float32_convolutions
from ..render import prepare_camera, rasterize
from .loss import psnr, ssim
from .outputs import view_stem

__all__ = ["LPIPS_NETS", "LpipsMetric", "describe_metrics", "error_triptych", "evaluate", "lpips_metric", "render_view"]


LPIPS_NETS = ("vgg", "alex")  # VGG first: the paper's and INRIA's; AlexNet: gsplat's default
LPIPS_BATCH = 8
# Pixels per LPIPS batch: VGG's activations take about 0.9 GB per 800 x 533 image (measured on the
# CPU), so eight such images made the evaluation's peak 14 GB on an H100 against 2.2 GB for the
# training. Each batch holds at most this many pixels, and at least one image.
LPIPS_BATCH_PIXELS = 1_000_000


class LpipsMetric:
    """The LPIPS networks of an evaluation (VGG and AlexNet), loaded once per run.

    ``nets[name]`` is the network, or absent when its weights could not be loaded; ``note`` then
    says why and how to get them. A missing network is reported as null, never estimated.
    ``nets`` given ({name: LPIPS}) are used as they are, none loaded (a benchmark's or a test's).
    """

    def __init__(self, device, nets: dict | None = None):
        from ..lpips import WeightsUnavailable, load_lpips

        if nets is not None:
            self.nets, self.note = dict(nets), None
            return
        self.nets, reasons = {}, []
        for name in LPIPS_NETS:
            try:
                self.nets[name] = load_lpips(name, device)
            except (WeightsUnavailable, InputError) as err:
                reasons.append(f"LPIPS-{name}: {err}")
        self.note = "; ".join(reasons) or None

    def scores(self, images: list[torch.Tensor], targets: list[torch.Tensor]) -> dict[str, list[float | None]]:
        """{"lpips_vgg": [...], "lpips_alex": [...]} of [H, W, 3] image/target pairs in [0, 1], in
        batches of images of one size (at most ``LPIPS_BATCH`` images and ``LPIPS_BATCH_PIXELS``
        pixels), without autograd. An image smaller than a net takes (16 px
        for VGG, 31 px for AlexNet) gets None from it (:meth:`too_small` words the note)."""
        out = {f"lpips_{name}": [] for name in self.nets}
        start = 0
        while start < len(images):
            end = start + 1
            pixels = images[start].shape[0] * images[start].shape[1]
            while (
                end < len(images)
                and end - start < LPIPS_BATCH
                and (end - start + 1) * pixels <= LPIPS_BATCH_PIXELS
                and images[end].shape == images[start].shape
            ):
                end += 1
            a = torch.stack([x.clamp(0, 1).permute(2, 0, 1) for x in images[start:end]])
            b = torch.stack([x.permute(2, 0, 1) for x in targets[start:end]])
            with torch.no_grad():
                for name, net in self.nets.items():
                    if min(a.shape[2:]) < net.min_size:
                        out[f"lpips_{name}"] += [None] * len(a)
                    else:
                        out[f"lpips_{name}"] += net(a, b).tolist()
            start = end
        return out

    def too_small(self, per_view: list[dict]) -> list[str]:
        """Notes on the views that a net could not score because they are too small."""
        notes = []
        for name, net in self.nets.items():
            count = sum(f"lpips_{name}" in entry and entry[f"lpips_{name}"] is None for entry in per_view)
            if count:
                notes.append(
                    f"LPIPS-{name}: {count} image(s) smaller than its {net.min_size} x {net.min_size} pixels not scored"
                )
        return notes


def lpips_metric(device) -> LpipsMetric:
    """The LPIPS networks for :func:`evaluate`; build it once per run."""
    return LpipsMetric(device)


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
    lpips: LpipsMetric | None = None,
    ranks=None,
    render_round=None,
) -> dict:
    """Metrics over ``views`` (means over views) and, with ``save_dir``, one triptych PNG per view.

    ``render(model, view, background, antialiased) -> (image, alpha, info)`` draws a view (cdcgs's
    rasterizer by default, each view's camera prepared once; the benchmarks pass a peer's to score
    it the same way). ``lpips``: what :func:`lpips_metric` returned (built here when not given).

    Returns PSNR, SSIM, LPIPS-VGG and LPIPS-Alex (``lpips_vgg``, ``lpips_alex``: null when the
    network's weights are unavailable, with the reason in ``lpips_note``), each a mean over views
    and per view in ``per_view``; render frames per second; the number of Gaussians.

    ``ranks`` (a :class:`cdcgs.train.distributed.Ranks` of several processes): each process
    scores the views ``rank``, ``rank + world``, ...; every process gets all the metrics, in the
    views' order, and only rank 0 writes the pictures (the others send theirs as PNG bytes).

    ``render_round(round_views) -> image or None``: a render that every process of ``ranks`` takes
    part in (a sharded scene's), used instead of ``render``. The views go in rounds, view
    ``k * world + r`` to process r in round k (each process's share, as above); every process
    calls it once a round with every process's view of the round (None past the views' end) and
    gets its own image (None where its view is None). ``num_gaussians`` is then ``model.num``, this
    process's slice (:meth:`cdcgs.train.trainer.Trainer._evaluate` puts the scene's there).
    """
    if not views:
        return {"views": 0}
    rank, world = (ranks.rank, ranks.world) if ranks is not None else (0, 1)
    all_views, views = views, views[rank::world]
    if render is None and render_round is None:
        cameras = {id(view): prepare_camera(view.viewmat, view.K, view.width, view.height) for view in views}

        def render(model, view, background, antialiased):
            return render_view(model, view, background, antialiased, camera=cameras[id(view)])

    if render_round is not None:
        rounds = -(-len(all_views) // world)

        def draw(k: int):  # this process's image of round k, or None past its share
            round_views = [all_views[v] if v < len(all_views) else None for v in range(k * world, (k + 1) * world)]
            return render_round(round_views)

    else:
        rounds = len(views)

        def draw(k: int):
            return render(model, views[k], background, antialiased)[0]  # the render's buffers go at once

    device = model.device
    lpips = lpips if lpips is not None else lpips_metric(device)
    per_view, pending = [], []  # pending: (entry, image, target) awaiting LPIPS, at most a batch

    def score_pending():
        scores = lpips.scores([p[1] for p in pending], [p[2] for p in pending])
        for key, values in scores.items():
            for (entry, _, _), value in zip(pending, values):
                entry[key] = value
        pending.clear()

    pictures = []  # (file name, PNG bytes) of this process's views, for rank 0 to write
    if save_dir and rank == 0:
        os.makedirs(save_dir, exist_ok=True)
    for k in range(rounds):
        image = draw(k)
        if k >= len(views):  # a round past this process's share: it took part in the render only
            continue
        view = views[k]
        gt = view.image.to(device).float() / 255.0
        with float32_convolutions():  # kornia's SSIM is a convolution too: full float32, no cuDNN workspace
            score = ssim(image, gt).item()
        per_view.append({"name": view.name, "psnr": psnr(image, gt).item(), "ssim": score})
        if lpips.nets:
            pending.append((per_view[-1], image, gt))  # scored a batch at a time, not all kept
            if len(pending) == LPIPS_BATCH:
                score_pending()
        if save_dir:
            from PIL import Image

            name = f"{view_stem(view.name)}.png"
            if world == 1:
                Image.fromarray(error_triptych(gt, image)).save(os.path.join(save_dir, name))
            else:
                buffer = io.BytesIO()
                Image.fromarray(error_triptych(gt, image)).save(buffer, format="png")
                pictures.append((name, buffer.getvalue()))
    score_pending()
    notes = lpips.too_small(per_view)
    # Render speed: every view once more, timed after the first pass warmed everything up.
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    for k in range(rounds):
        draw(k)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - start
    if world > 1:
        shares = ranks.all_gather_object((per_view, seconds, notes))
        per_view = [None] * len(all_views)
        for r, (entries, _, _) in enumerate(shares):
            per_view[r::world] = entries
        seconds = sum(share[1] for share in shares)
        notes = sorted({note for share in shares for note in share[2]})
        sent = ranks.gather_object(pictures)
        if save_dir and rank == 0:
            for name, data in (item for share in sent for item in share):
                with open(os.path.join(save_dir, name), "wb") as f:
                    f.write(data)
        views = all_views
    metrics = {
        "views": len(views),
        "psnr": float(np.mean([v["psnr"] for v in per_view])),
        "ssim": float(np.mean([v["ssim"] for v in per_view])),
        **{f"lpips_{name}": _mean(per_view, f"lpips_{name}") for name in LPIPS_NETS},
        "render_fps": len(views) / max(seconds, 1e-9),
        "num_gaussians": model.num,
        "per_view": per_view,
    }
    notes = ([lpips.note] if lpips.note else []) + notes
    if notes:
        metrics["lpips_note"] = "; ".join(notes)
    return metrics


def describe_metrics(metrics: dict) -> str:
    """One line of an evaluation's means: PSNR, SSIM, LPIPS-VGG, LPIPS-Alex (or how to get LPIPS)."""
    parts = [f"PSNR {metrics['psnr']:.2f} dB", f"SSIM {metrics['ssim']:.4f}"]
    for name, label in (("vgg", "LPIPS-VGG"), ("alex", "LPIPS-Alex")):
        if metrics.get(f"lpips_{name}") is not None:
            parts.append(f"{label} {metrics[f'lpips_{name}']:.4f}")
    if metrics.get("lpips_vgg") is None or metrics.get("lpips_alex") is None:
        parts.append("LPIPS unavailable (run `cdcgs weights lpips` once to get its weights)")
    return ", ".join(parts) + f" over {metrics['views']} views"


def _mean(per_view: list[dict], key: str) -> float | None:
    values = [entry[key] for entry in per_view if entry.get(key) is not None]
    return float(np.mean(values)) if values else None
