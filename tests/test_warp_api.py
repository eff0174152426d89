"""The kernels work from plain Warp, without torch, as the README shows."""

import os
import subprocess
import sys

import numpy as np
import torch

import cdcgs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "examples"))
import warp_launch  # noqa: E402


def test_kernels_do_not_import_torch():
    code = "import sys, cdcgs.kernels; assert 'torch' not in sys.modules, 'cdcgs.kernels imported torch'"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_plain_warp_launch_matches_rasterize(device):
    means, quats, scales, opacities, sh, viewmat, K, width, height = warp_launch.demo_scene(n=300)
    image = warp_launch.render(means, quats, scales, opacities, sh, viewmat, K, width, height, device=device)
    t = lambda a: torch.from_numpy(a).to(device)
    expected, _, _ = cdcgs.rasterize(
        t(means), t(quats), t(scales), t(opacities), t(sh), viewmat=viewmat, K=K, width=width, height=height,
        background=[1.0, 1.0, 1.0],
    )  # fmt: skip
    assert image.shape == (height, width, 3)
    assert (image < 0.99).any(), "the demo scene must not be empty"
    np.testing.assert_allclose(image, expected.cpu().numpy(), atol=1e-6)

