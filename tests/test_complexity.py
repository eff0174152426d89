"""CDC-GS complexity: the high-pass maps and the per-Gaussian complexity kernel."""

import pytest
import reference
import torch
from conftest import make_scene

import cdcgs
from cdcgs.complexity import complexity_map, gaussian_complexity, high_frequency, luma


def test_luma_uses_proper_rgb_weights():
    image = torch.tensor([[[255, 0, 0], [0, 255, 0], [0, 0, 255]]], dtype=torch.uint8)
    torch.testing.assert_close(luma(image), torch.tensor([[0.299, 0.587, 0.114]]))


@pytest.mark.parametrize("method", ["dwt", "dwt2", "sobel", "scharr", "laplacian"])
def test_constant_image_has_no_high_frequency(method):
    assert (high_frequency(torch.full((13, 17), 0.4), method) == 0).all()


def test_dwt_step_edge_responds_only_at_the_edge():
    # A vertical step between columns 4 and 5 (Haar pairs (4, 5)): one DWT level sees it only in
    # those two columns, where the detail is +-(b - a)/2, the same everywhere after normalising.
    y = torch.zeros(8, 12)
    y[:, 5:] = 1.0
    hf = high_frequency(y, "dwt")
    expected = torch.zeros(8, 12)
    expected[:, [4, 5]] = 1.0
    torch.testing.assert_close(hf, expected, atol=1e-6, rtol=0)
    # An edge on a Haar pair boundary (between columns 5 and 6) is invisible to one level:
    y = torch.zeros(8, 12)
    y[:, 6:] = 1.0
    assert high_frequency(y, "dwt").abs().max() < 1e-6
    # ... but not to two levels, unless it is also on a level-2 boundary (columns 7 and 8 are not).
    y = torch.zeros(8, 12)
    y[:, 6:] = 1.0
    hf2 = high_frequency(y, "dwt2")
    assert hf2[:, 4:8].max() > 0.5 and hf2[:, :4].abs().max() < 1e-6 and hf2[:, 8:].abs().max() < 1e-6


def test_odd_sizes_are_cropped_back():
    hf = high_frequency(torch.rand(13, 17), "dwt")
    assert hf.shape == (13, 17) and hf.min() == 0 and hf.max() == 1


def test_complexity_map_is_uint8_on_the_image_device(device):
    image = (torch.rand(20, 30, 3) * 255).to(torch.uint8).to(device)
    m = complexity_map(image)
    assert m.dtype == torch.uint8 and m.shape == (20, 30) and m.device.type == device and m.max() == 255


def dense_complexity(weights: torch.Tensor, hf: torch.Tensor):
    """Reference: per Gaussian max / sum / count over pixels of HF * max(w, 1e-4) / w_max."""
    contributing = weights > 0
    floored = torch.where(contributing, weights.clamp_min(1e-4), torch.zeros_like(weights))
    w_max = floored.max(dim=1, keepdim=True).values.clamp_min(1e-4)
    value = torch.where(contributing, hf.reshape(-1, 1) * floored / w_max, torch.zeros_like(weights))
    return value.max(dim=0).values, value.sum(dim=0), contributing.sum(dim=0)


@pytest.mark.parametrize("seed", [21, 22])
def test_gaussian_complexity_matches_dense_reference(device, seed):
    scene = make_scene(300, 61, 37, sh_degree=0, seed=seed)
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=61, height=37
    )
    g = torch.Generator().manual_seed(seed)
    hf_map = (torch.rand(37, 61, generator=g) * 255).to(torch.uint8)
    max_out, sum_out, count = gaussian_complexity(info, hf_map.to(device))
    d = [t.double() for t in scene.tensors()]
    *_, weights = reference.render(*d, viewmat=scene.viewmat.double(), K=scene.K.double(), width=61, height=37)
    ref_max, ref_sum, ref_count = dense_complexity(weights, hf_map.double() / 255.0)
    assert (ref_count > 0).sum() > 20
    torch.testing.assert_close(count.cpu().long(), ref_count)
    torch.testing.assert_close(max_out.cpu().double(), ref_max, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(sum_out.cpu().double(), ref_sum, atol=1e-4, rtol=1e-4)


def test_bad_map_is_refused(device):
    scene = make_scene(40, 32, 24, sh_degree=0, seed=3, hard_cases=False)
    _, _, info = cdcgs.rasterize(
        *[t.to(device) for t in scene.tensors()], viewmat=scene.viewmat, K=scene.K, width=32, height=24
    )
    with pytest.raises(ValueError, match="hf_map must be a uint8"):
        gaussian_complexity(info, torch.zeros(24, 31, dtype=torch.uint8, device=device))
    with pytest.raises(ValueError, match="hf_map must be a uint8"):
        gaussian_complexity(info, torch.zeros(24, 32, device=device))
