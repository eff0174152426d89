"""CDC-GS complexity: per-image high-frequency maps and the per-Gaussian complexity Gamma.

Maps (CDC-GS.md section 1): luma Y = 0.299 R + 0.587 G + 0.114 B at training resolution; one level
of the 2-D Haar DWT (ptwt), LL band zeroed, inverse DWT, absolute value, min-max normalised to
[0, 1]; or two levels (only the coarsest LL zeroed); or Sobel, Scharr, Laplacian magnitudes
(kornia) for the ablation. Kept as uint8 (x 255) on the training device.

Gamma (section 2): per view, the max over the pixels a Gaussian composites of
HF(p) * w_i(p) / w_max(p), computed by ``complexity_kernel`` (exact atomic max).
"""

from __future__ import annotations

import kornia
import ptwt
import torch
import warp as wp

from .interop import warp_scope, wp_array
from .kernels.binning import TILE_SIZE
from .kernels.blend import complexity_kernel

METHODS = ("dwt", "dwt2", "sobel", "scharr", "laplacian")
LUMA = (0.299, 0.587, 0.114)


def luma(image: torch.Tensor) -> torch.Tensor:
    """[H, W] luma in [0, 1] of an [H, W, 3] uint8 or float image (proper RGB weights)."""
    rgb = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    return rgb @ rgb.new_tensor(LUMA)


def _normalise(x: torch.Tensor) -> torch.Tensor:
    """Min-max to [0, 1]; a response below 1e-6 (luma units) is rounding noise of a flat image."""
    lo, hi = x.min(), x.max()
    return (x - lo) / (hi - lo) if hi - lo > 1e-6 else torch.zeros_like(x)


def high_frequency(y: torch.Tensor, method: str = "dwt") -> torch.Tensor:
    """[H, W] high-frequency magnitude in [0, 1] of a luma image [H, W] (min-max normalised)."""
    h, w = y.shape
    if method in ("dwt", "dwt2"):
        level = 1 if method == "dwt" else 2
        coeffs = list(ptwt.wavedec2(y[None].double(), "haar", level=level))
        coeffs[0] = torch.zeros_like(coeffs[0])  # the coarsest approximation (LL) only
        detail = ptwt.waverec2(tuple(coeffs), "haar")[0, :h, :w]  # crop the padding back
        return _normalise(detail.abs()).float()
    image = y[None, None]
    if method == "sobel":
        response = kornia.filters.sobel(image, normalized=True)
    elif method == "scharr":
        kernel = y.new_tensor([[3.0, 0.0, -3.0], [10.0, 0.0, -10.0], [3.0, 0.0, -3.0]]) / 32.0
        gx = kornia.filters.filter2d(image, kernel[None], border_type="replicate")
        gy = kornia.filters.filter2d(image, kernel.T[None], border_type="replicate")
        response = torch.sqrt(gx * gx + gy * gy)
    elif method == "laplacian":
        response = kornia.filters.laplacian(image, kernel_size=3).abs()
    else:
        raise ValueError(f"complexity method must be one of {', '.join(METHODS)}, got {method!r}")
    return _normalise(response[0, 0])


def complexity_map(image: torch.Tensor, method: str = "dwt") -> torch.Tensor:
    """[H, W] uint8 complexity map (HF x 255) of an [H, W, 3] image, on the image's device."""
    return (high_frequency(luma(image), method) * 255.0 + 0.5).to(torch.uint8)


def gaussian_complexity(info, hf_map: torch.Tensor, opacities: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(max [N], sum [N], count [N] int32) over one render's pixels of HF * w / w_max per Gaussian.

    ``info`` is the RasterizeInfo of the render; ``hf_map`` its view's [H, W] uint8 map.
    Gaussians that composite no pixel get max 0 and count 0.
    """
    if hf_map.shape != (info.height, info.width) or hf_map.dtype != torch.uint8:
        raise ValueError(f"hf_map must be a uint8 [{info.height}, {info.width}] map, got {hf_map.dtype} {list(hf_map.shape)}")
    n = info.means2d.shape[0]
    device = info.means2d.device
    opacities = info.opacities if opacities is None else opacities
    max_out = torch.zeros(n, device=device)
    sum_out = torch.zeros(n, device=device)
    count_out = torch.zeros(n, dtype=torch.int32, device=device)
    tiles_y, tiles_x = info.tile_ranges.shape[:2]
    with warp_scope(device):
        wp.launch(
            complexity_kernel,
            tiles_x * tiles_y * TILE_SIZE * TILE_SIZE,
            inputs=[
                wp_array(info.tile_ranges.reshape(-1, 2), wp.int32), wp_array(info.sorted_gauss_ids, wp.int32),
                wp_array(info.means2d.detach().contiguous(), wp.vec2), wp_array(info.conics.detach().contiguous(), wp.vec3),
                wp_array(opacities.detach().contiguous(), wp.float32), wp_array(info.last_contributor, wp.int32),
                wp_array(hf_map.to(device).contiguous(), wp.uint8), info.width, info.height, tiles_x,
            ],  # fmt: skip
            outputs=[wp_array(max_out, wp.float32), wp_array(sum_out, wp.float32), wp_array(count_out, wp.int32)],
            block_dim=TILE_SIZE * TILE_SIZE,
        )
    return max_out, sum_out, count_out
