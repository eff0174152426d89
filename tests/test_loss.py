"""The fused L1 + D-SSIM loss (cdcgs.kernels.loss) against kornia's SSIM and torch's L1 in float64."""

import kornia
import pytest
import torch
from helpers import DEFAULT_DEVICE, tiny_config

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


@pytest.mark.parametrize("size", [(6, 6), (7, 19), (33, 24)])  # the smallest allowed, borders everywhere
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
