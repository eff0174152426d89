"""The fused L1 + D-SSIM loss (cdcgs.kernels.loss) against kornia's SSIM and torch's L1 in float64,
and each of its separable passes against a brute-force float64 reference."""

import kornia
import numpy as np
import pytest
import torch
import warp as wp
from helpers import DEFAULT_DEVICE, tiny_config

from cdcgs.kernels import (
    ssim_l1_backward_kernel,
    ssim_l1_backward_rows_kernel,
    ssim_l1_forward_kernel,
    ssim_l1_forward_rows_kernel,
    ssim_l1_launch_size,
)
from cdcgs.train.loss import fused_photometric_loss, mse_to_psnr, photometric_loss, psnr
from cdcgs.train.trainer import Trainer


def reference(image: torch.Tensor, target: torch.Tensor, weight: float) -> torch.Tensor:
    """The loss in float64 with kornia and torch (the definition the training used before)."""
    l1 = (image - target).abs().mean()
    ssim = kornia.metrics.ssim(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], window_size=11).mean()
    return (1 - weight) * l1 + weight * (1 - ssim)


def pair(height: int, width: int, seed: int = 0):
    """A uint8 photo and a render near it, with a few pixels equal to it (L1's kink) and a few
    outside [0, 1] (the PSNR clamps them)."""
    g = torch.Generator().manual_seed(seed)
    photo = torch.randint(0, 256, (height, width, 3), generator=g, dtype=torch.uint8)
    target = photo.float() / 255
    image = (target + 0.2 * torch.randn(height, width, 3, generator=g)).clamp(-0.1, 1.1)
    image[0, 0] = target[0, 0]
    image[-1, 2, 1] = target[-1, 2, 1]
    return image, photo


# The smallest allowed, borders everywhere; wider than tall and taller than wide, where each
# window of the short side crosses both of its borders.
@pytest.mark.parametrize("size", [(6, 6), (7, 19), (33, 24), (6, 40), (40, 6)])
@pytest.mark.parametrize("weight", [0.0, 0.2, 1.0])
@pytest.mark.parametrize("target_type", ["uint8", "float32"])
def test_value_and_gradient_match_kornia_and_torch(device, size, weight, target_type):
    image, photo = pair(*size, seed=size[0] + 3 * size[1])
    target = photo if target_type == "uint8" else photo.float() / 255
    x = image.double().requires_grad_()
    expected = reference(x, (photo.float() / 255).double(), weight)  # the kink where they are equal in float32
    expected.backward()

    rendered = image.to(device).requires_grad_()
    loss, mse = fused_photometric_loss(rendered, target.to(device), weight)
    (2.5 * loss).backward()  # the upstream gradient is read on the device
    assert loss.item() == pytest.approx(expected.item(), rel=2e-6, abs=1e-7)
    assert rendered.grad.shape == image.shape and not mse.requires_grad
    expected_grad = 2.5 * x.grad  # float32 against float64: errors of ~1e-5 of the largest entry
    scale = expected_grad.abs().max().item()
    torch.testing.assert_close(rendered.grad.cpu().double(), expected_grad, rtol=1e-3, atol=1e-4 * scale)
    clamped_mse = ((image.double().clamp(0, 1) - (photo.float() / 255).double()) ** 2).mean()
    assert mse.item() == pytest.approx(clamped_mse.item(), rel=1e-5)
    assert mse_to_psnr(mse).item() == pytest.approx(psnr(image, photo.float() / 255).item(), abs=1e-4)


# The brute-force reference of the passes: float64 numpy, the 11 x 11 window taken whole (not as
# two passes), the padding numpy's "reflect" (index -1 reads 1, as kornia's), the backward
# gathers as the scatters they transpose.
GAUSSIAN = kornia.filters.get_gaussian_kernel1d(11, 1.5).double().numpy().reshape(11)


def reflected(n: int) -> np.ndarray:
    """The source index of each of the n + 10 positions -5 .. n + 4 under reflect padding."""
    return np.pad(np.arange(n), 5, mode="reflect")


def window_sums(values: np.ndarray, rows_only: bool = False) -> np.ndarray:
    """Σ over the window of weight × value at each pixel of an [H, W, C] array; along the row alone
    with ``rows_only``."""
    if rows_only:
        padded = np.pad(values, ((0, 0), (5, 5), (0, 0)), mode="reflect")
        return np.lib.stride_tricks.sliding_window_view(padded, 11, axis=1) @ GAUSSIAN
    padded = np.pad(values, ((5, 5), (5, 5), (0, 0)), mode="reflect")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (11, 11), axis=(0, 1))  # [H, W, C, 11, 11]
    return np.einsum("hwcij,ij->hwc", windows, np.outer(GAUSSIAN, GAUSSIAN))


def scatter_windows(values: np.ndarray, rows_only: bool = False) -> np.ndarray:
    """The transpose of :func:`window_sums`: each pixel's value spread over the pixels its window
    reads, with their weights."""
    height, width = values.shape[:2]
    source_y, source_x = reflected(height), reflected(width)
    row_taps = [(5, 1.0)] if rows_only else list(enumerate(GAUSSIAN))  # tap 5: the window's own row
    out = np.zeros_like(values)
    for ky, weight_y in row_taps:
        for kx, weight_x in enumerate(GAUSSIAN):
            rows = source_y[np.arange(height) + ky][:, None]
            columns = source_x[np.arange(width) + kx][None, :]
            np.add.at(out, (rows, columns), weight_y * weight_x * values)
    return out


def ssim_and_derivatives(moments: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """SSIM from the window's [μx, μy, E[x²], E[y²], E[xy]], and its derivatives with respect to
    μx, E[x²] and E[xy] (the other moments held) by autograd, in float64."""
    mx, my, sxx, syy, sxy = (torch.tensor(m, requires_grad=True) for m in moments)
    c1, c2 = 0.01**2, 0.03**2
    numerator = (2 * mx * my + c1) * (2 * (sxy - mx * my) + c2)
    denominator = (mx**2 + my**2 + c1) * (sxx - mx**2 + syy - my**2 + c2) + 1e-12
    ssim = numerator / denominator
    ssim.sum().backward()
    return ssim.detach().numpy(), [t.grad.numpy() for t in (mx, sxx, sxy)]


@pytest.mark.parametrize("size", [(6, 40), (40, 6), (13, 11)])
@pytest.mark.parametrize("target_type", ["uint8", "float32"])
def test_each_pass_matches_a_brute_force_reference(device, size, target_type):
    """The four kernels launched from Warp alone as docs/kernels.md says, each compared with the
    brute-force reference given the previous kernel's output: the horizontal moments, the derivative
    maps and the loss, the horizontal gathers, the gradient. Tolerances (float32 kernels): 1e-6 of
    the largest entry for the moments, whose inputs are in [-0.1, 1.1]; for the rest 1e-3 relative
    and 1e-5 of the largest entry (SSIM divides by small variances in places)."""
    height, width = size
    image, photo = pair(height, width, seed=height + 5 * width)
    target = photo if target_type == "uint8" else photo.float() / 255
    x = image.double().numpy()
    y = (photo.double() / 255).numpy()
    weight, grad_loss = 0.2, 2.5
    inv_count = 1.0 / (3 * height * width)

    image_wp = wp.array(image.numpy(), dtype=wp.vec3, device=device)
    target_wp = wp.array(target.numpy(), dtype=wp.uint8 if target_type == "uint8" else wp.float32, device=device)
    row_moments = wp.empty((5, height, width), dtype=wp.vec3, device=device)
    sums = wp.zeros(2, dtype=wp.float32, device=device)
    maps = [wp.empty((height, width), dtype=wp.vec3, device=device) for _ in range(3)]
    row_gathers = wp.empty((3, height, width), dtype=wp.vec3, device=device)
    grad_image = wp.empty((height, width), dtype=wp.vec3, device=device)
    grad_loss_wp = wp.array([grad_loss], dtype=wp.float32, device=device)
    pixels = height * width
    wp.launch(ssim_l1_forward_rows_kernel, pixels, inputs=[image_wp, target_wp], outputs=[row_moments], device=device)
    wp.launch(
        ssim_l1_forward_kernel,
        ssim_l1_launch_size(height, width),
        inputs=[image_wp, target_wp, weight, inv_count, row_moments],
        outputs=[sums, *maps],
        device=device,
    )
    wp.launch(ssim_l1_backward_rows_kernel, pixels, inputs=maps, outputs=[row_gathers], device=device)
    wp.launch(
        ssim_l1_backward_kernel,
        pixels,
        inputs=[image_wp, target_wp, weight, inv_count, grad_loss_wp, row_gathers],
        outputs=[grad_image],
        device=device,
    )

    def close(actual, expected, rtol=1e-3, atol=1e-5):
        scale = np.abs(expected).max()
        assert scale > 0
        np.testing.assert_allclose(actual, expected, rtol=rtol, atol=atol * scale)

    products = [x, y, x * x, y * y, x * y]
    for ours, product in zip(row_moments.numpy(), products):
        close(ours, window_sums(product, rows_only=True), rtol=0, atol=1e-6)
    ssim, derivatives = ssim_and_derivatives([window_sums(product) for product in products])
    ours_maps = [m.numpy().astype(np.float64) for m in maps]
    for ours, expected in zip(ours_maps, derivatives):
        close(ours, expected)
    loss = (1 - weight) * np.abs(x - y).mean() + weight * (1 - ssim.mean())
    assert sums.numpy()[0] == pytest.approx(loss, rel=2e-6)
    assert sums.numpy()[1] == pytest.approx(((x.clip(0, 1) - y) ** 2).mean(), rel=1e-5)

    for ours, expected in zip(row_gathers.numpy(), ours_maps):
        close(ours, scatter_windows(expected, rows_only=True))
    acc_mean, acc_square, acc_cross = (scatter_windows(m) for m in ours_maps)
    sign = np.sign(image.numpy() - photo.numpy() / np.float32(255))  # the kink where they are equal in float32
    expected = grad_loss * inv_count * ((1 - weight) * sign - weight * (acc_mean + 2 * x * acc_square + y * acc_cross))
    close(grad_image.numpy(), expected)


def test_gradient_is_a_finite_difference_of_the_loss(device):
    """Independent of kornia: central differences of the fused loss itself (float32, so a few
    pixels and a loose tolerance), at border and interior pixels."""
    image, photo = pair(12, 9, seed=5)
    image, photo = image.to(device), photo.to(device)
    rendered = image.clone().requires_grad_()
    fused_photometric_loss(rendered, photo, 0.2)[0].backward()
    h = 1e-2
    for y, x, c in [(0, 1, 1), (0, 4, 0), (5, 8, 2), (11, 3, 1), (6, 4, 0)]:
        up, down = image.clone(), image.clone()
        up[y, x, c] += h
        down[y, x, c] -= h
        # Away from L1's kink: the step must not cross image == target.
        assert abs(image[y, x, c].item() - photo[y, x, c].item() / 255) > h
        numeric = (fused_photometric_loss(up, photo, 0.2)[0] - fused_photometric_loss(down, photo, 0.2)[0]) / (2 * h)
        assert rendered.grad[y, x, c].item() == pytest.approx(numeric.item(), rel=2e-2, abs=2e-6)


@pytest.mark.parametrize(
    "image,target,weight,message",
    [
        (torch.zeros(8, 8, 3, dtype=torch.float64), torch.zeros(8, 8, 3), 0.2, "image must be a float32 [H, W, 3]"),
        (torch.zeros(8, 8, 4), torch.zeros(8, 8, 4), 0.2, "image must be a float32 [H, W, 3]"),
        (
            torch.zeros(8, 8, 3),
            torch.zeros(8, 9, 3),
            0.2,
            "target must be a uint8 or float32 tensor of the image's shape",
        ),
        (torch.zeros(8, 8, 3), torch.zeros(8, 8, 3, dtype=torch.int32), 0.2, "target must be a uint8 or float32"),
        (torch.zeros(5, 8, 3), torch.zeros(5, 8, 3), 0.2, "images must be larger than 5 pixels"),
        (torch.zeros(8, 8, 3), torch.zeros(8, 8, 3), 1.5, "ssim_weight must be in [0, 1]"),
    ],
)
def test_bad_inputs_are_named(image, target, weight, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        fused_photometric_loss(image, target, weight)


def test_training_with_the_fused_loss_follows_the_reference_loss(tiny_scene, tmp_path):
    """The first iterations of a training give the same losses either way (float32 rounding)."""
    losses = {}
    for fused in (True, False):
        trainer = Trainer(tiny_config(tiny_scene, tmp_path / str(fused), iters=3, fused_loss=fused, log_every=1), {})
        trainer.run()
        losses[fused] = trainer.history["loss"]
    assert losses[True] == pytest.approx(losses[False], rel=1e-4)
    image, photo = (t.to(DEFAULT_DEVICE) for t in pair(20, 20))
    fused, _ = fused_photometric_loss(image, photo, 0.2)
    assert fused.item() == pytest.approx(photometric_loss(image, photo.float() / 255, 0.2).item(), rel=1e-5)
