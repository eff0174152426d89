"""Finite-difference checks of gradients on a few Gaussians.

The Warp kernels are float32, so their gradients are checked with central differences on a
smooth scene: Gaussians wide enough that every pixel of the small image is inside every
footprint, opacities well below the 0.99 clamp and transmittance far from the 1e-4 stop, so no
threshold is crossed by a perturbation. The float64 reference, whose autograd is the oracle of
the other gradient tests, is itself checked with torch.autograd.gradcheck in float64.
"""

import pytest
import reference
import torch

import cdcgs

WIDTH, HEIGHT = 20, 14
K = torch.tensor([[18.0, 0.0, 9.7], [0.0, 18.0, 7.2], [0.0, 0.0, 1.0]])
VIEW = torch.tensor([[0.96, 0.0, -0.28, 0.1], [0.0, 1.0, 0.0, -0.05], [0.28, 0.0, 0.96, 0.2], [0.0, 0.0, 0.0, 1.0]])


def smooth_scene(dtype=torch.float32):
    g = torch.Generator().manual_seed(3)
    n = 4
    cam = torch.tensor([[0.1, -0.1, 3.0], [-0.2, 0.15, 3.5], [0.25, 0.05, 4.0], [0.0, 0.0, 4.5]])
    R, t = VIEW[:3, :3], VIEW[:3, 3]
    means = (cam - t) @ R
    quats = torch.randn(n, 4, generator=g)
    scales = torch.tensor([[1.5, 2.0, 1.0], [2.2, 1.3, 1.7], [1.8, 1.8, 2.5], [2.5, 2.0, 1.4]])
    opacities = torch.tensor([0.35, 0.5, 0.45, 0.6])
    sh = torch.randn(n, 16, 3, generator=g) * 0.2
    background = torch.tensor([0.3, 0.6, 0.2])
    return [t.to(dtype) for t in (means, quats, scales, opacities, sh, background)]


def loss_fn(render, cot_image, cot_alpha, cot_depth):
    def loss(*tensors):
        image, alpha, depth = render(*tensors)
        return (
            (image.double() * cot_image).sum() + (alpha.double() * cot_alpha).sum() + (depth.double() * cot_depth).sum()
        )

    return loss


def warp_render(device, antialiased):
    def render(means, quats, scales, opacities, sh, background):
        image, alpha, info = cdcgs.rasterize(
            means,
            quats,
            scales,
            opacities,
            sh,
            viewmat=VIEW,
            K=K,
            width=WIDTH,
            height=HEIGHT,
            background=background,
            antialiased=antialiased,
            render_depth=True,
        )
        return image, alpha, info.depth

    return render


@pytest.mark.parametrize("antialiased", [False, True])
def test_warp_gradients_match_central_differences(device, antialiased):
    tensors = [t.to(device) for t in smooth_scene()]
    g = torch.Generator().manual_seed(4)
    cots = [
        torch.randn(HEIGHT, WIDTH, 3, generator=g),
        torch.randn(HEIGHT, WIDTH, generator=g),
        torch.randn(HEIGHT, WIDTH, generator=g) * 0.1,
    ]
    loss = loss_fn(warp_render(device, antialiased), *[c.to(device, torch.float64) for c in cots])
    # Preconditions of a smooth scene: full coverage, no clamp, no early stop.
    with torch.no_grad():
        _, alpha, info = cdcgs.rasterize(*tensors[:5], viewmat=VIEW, K=K, width=WIDTH, height=HEIGHT)
        assert (info.tile_counts == 2).all()
        assert alpha.min() > 0.5 and alpha.max() < 0.99
    leaves = [t.clone().requires_grad_() for t in tensors]
    loss(*leaves).backward()
    steps = {0: 1e-3, 1: 1e-3, 2: 1e-3, 3: 1e-3, 4: 1e-3, 5: 1e-3}
    names = ["means", "quats", "scales", "opacities", "sh", "background"]
    for k, name in enumerate(names):
        analytic = leaves[k].grad.double().cpu().reshape(-1)
        flat = tensors[k].reshape(-1)
        numeric = torch.zeros_like(analytic)
        for j in range(flat.numel()):
            plus = [t.clone() for t in tensors]
            minus = [t.clone() for t in tensors]
            plus[k].reshape(-1)[j] += steps[k]
            minus[k].reshape(-1)[j] -= steps[k]
            with torch.no_grad():
                numeric[j] = (loss(*plus) - loss(*minus)) / (2 * steps[k])
        scale = analytic.abs().max().item()
        assert scale > 0
        # float32 renders under a float64 loss: differences carry ~1e-3 relative noise.
        torch.testing.assert_close(
            analytic, numeric, atol=5e-3 * scale, rtol=1e-2, msg=lambda m, name=name: f"{name}: {m}"
        )


def test_reference_gradients_pass_gradcheck_in_float64():
    means, quats, scales, opacities, sh, background = (t.requires_grad_() for t in smooth_scene(torch.float64))

    def render(means, quats, scales, opacities, sh, background):
        image, alpha, depth, _ = reference.render(
            means,
            quats,
            scales,
            opacities,
            sh,
            viewmat=VIEW.double(),
            K=K.double(),
            width=8,
            height=6,
            background=background,
        )
        return image, alpha, depth

    assert torch.autograd.gradcheck(
        render, (means, quats, scales, opacities, sh, background), eps=1e-6, atol=1e-6, rtol=1e-4
    )
