import math
import os
import sys
from dataclasses import dataclass

import pytest
import torch
import warp as wp
from PIL import Image  # noqa: F401  before any pycolmap import (see cdcgs/io/colmap.py)

wp.config.log_level = wp.LOG_WARNING
sys.path.insert(0, os.path.dirname(__file__))


def test_devices() -> list[str]:
    """``cpu`` always, ``cuda`` when both torch and Warp see a GPU.

    CDCGS_TEST_DEVICES (e.g. "cuda") narrows the list. Where Warp has no CPU compiler (the GPU
    image's Warp comes without it) ``cpu`` is left out, and :func:`pytest_collection_modifyitems`
    skips the tests that run on the CPU only.
    """
    devices = ["cpu"] if wp.is_cpu_available() else []
    if torch.cuda.is_available() and wp.is_cuda_available():
        devices.append("cuda")
    wanted = os.environ.get("CDCGS_TEST_DEVICES")
    if wanted:
        devices = [d for d in devices if d in wanted.split(",")]
    return devices


test_devices.__test__ = False  # a helper, not a test


def pytest_collection_modifyitems(config, items):
    """Without ``cpu`` among the test devices, the tests not given another device are skipped,
    with the reason, instead of failing inside Warp's missing CPU compiler."""
    if "cpu" in test_devices():
        return
    skip = pytest.mark.skip(
        reason="a CPU test, and the CPU is not among the test devices (CDCGS_TEST_DEVICES, or Warp without its CPU compiler)"
    )
    for item in items:
        params = getattr(getattr(item, "callspec", None), "params", {})
        if params.get("device", "cpu") == "cpu":
            item.add_marker(skip)


@pytest.fixture(params=test_devices())
def device(request):
    return request.param


@dataclass
class Scene:
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int

    def to(self, device):
        fields = {
            k: (v.to(device) if isinstance(v, torch.Tensor) and k not in ("viewmat", "K") else v)
            for k, v in vars(self).items()
        }
        return Scene(**fields)

    def tensors(self):
        return [self.means, self.quats, self.scales, self.opacities, self.sh]


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """World-to-camera matrix of a camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(-up, z)  # y is down, so "up" points to -y
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = R
    view[:3, 3] = -R @ eye
    return view.float()


def make_scene(n=300, width=61, height=37, sh_degree=3, seed=0, hard_cases=True) -> Scene:
    """A random scene seen by a rotated camera with an off-centre principal point.

    With ``hard_cases`` it also holds Gaussians behind the camera, straddling the near plane,
    partly off-screen, very large, very thin, nearly transparent, nearly opaque and at equal depths.
    """
    g = torch.Generator().manual_seed(seed)
    viewmat = look_at((0.3, -0.4, -5.0), (0.0, 0.0, 0.0))
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, 0.47 * width], [0.0, 0.95 * f, 0.55 * height], [0.0, 0.0, 1.0]])
    # Gaussians in camera space, then moved to world space.
    cam = torch.randn(n, 3, generator=g) * torch.tensor([0.9, 0.6, 0.8]) + torch.tensor([0.0, 0.0, 5.0])
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 + math.log(0.08))
    opacities = torch.rand(n, generator=g) * 0.95 + 0.02
    if hard_cases:
        m = n // 12
        cam[0:m, 2] = -torch.rand(m, generator=g) * 3.0  # behind the camera
        cam[m : 2 * m, 2] = 0.01 + torch.rand(m, generator=g) * 0.3  # at the near plane
        cam[m : 2 * m, :2] *= 0.05
        cam[2 * m : 3 * m, 0] = cam[2 * m : 3 * m, 2] * (0.6 + 0.3 * torch.rand(m, generator=g))  # off the right edge
        scales[3 * m : 4 * m] = torch.rand(m, 3, generator=g) * 1.0 + 0.5  # very large
        scales[4 * m : 5 * m, 0] = 1e-3  # very thin
        scales[4 * m : 5 * m, 1] = 0.3
        transparent = torch.rand(m, generator=g) * 0.01  # nearly transparent, on both sides of 1/255
        # ... but not within 5% of 1/255, where whether a pixel passes the alpha threshold depends
        # on float rounding (the Gaussian is flat near its centre), so float32 and float64 differ.
        near = (transparent * 255 - 1).abs() < 0.05
        opacities[5 * m : 6 * m] = torch.where(near, transparent * 0.8, transparent)
        opacities[6 * m : 7 * m] = 1.0 - torch.rand(m, generator=g) * 1e-3  # nearly opaque
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    means = (cam - t) @ R  # R^T (cam - t)
    if hard_cases:
        # Equal depths: Gaussians sharing a mean have bit-identical depths in any implementation
        # (distinct means at one depth in exact arithmetic would differ by rounding), so their
        # order is the tie-break by index, which the renderer and the reference must both follow.
        means[7 * m : 8 * m] = means[7 * m : 7 * m + 3].repeat((m + 2) // 3, 1)[:m]
    quats = torch.randn(n, 4, generator=g)
    k = (sh_degree + 1) ** 2
    sh = torch.randn(n, k, 3, generator=g) * 0.2
    sh[:, 0] = torch.rand(n, 3, generator=g) * 1.6 - 0.4
    return Scene(means.contiguous(), quats, scales, opacities, sh, viewmat, K, width, height)


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """A procedural COLMAP scene of 16 views of 48 x 36 pixels and 1500 points."""
    from cdcgs.datasets.procedural import make_procedural_scene

    return make_procedural_scene(tmp_path_factory.mktemp("scene"), views=16, width=48, height=36, points=1500)
