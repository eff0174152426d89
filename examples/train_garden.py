"""MipNeRF-360 garden with CDC-GS: the project's main job.

The trainer is not in cdcgs yet; until it lands this script renders a procedural demo scene with
the differentiable Warp rasterizer from an orbit of cameras, and runs a few steps of gradient
descent on the Gaussians' colours against the first view, so that the command does real work.

    python examples/train_garden.py [--device cuda|cpu] [--out outputs/garden_demo] [--steps 50]
"""

import argparse
import math
import os
import time

import numpy as np
import torch

import cdcgs


def orbit_viewmat(angle: float, radius: float = 4.0, height: float = -1.0) -> torch.Tensor:
    """World-to-camera matrix of a camera on a circle around the origin, looking at it (y down)."""
    eye = torch.tensor([radius * math.sin(angle), height, -radius * math.cos(angle)], dtype=torch.float64)
    forward = -eye / eye.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), forward)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3], view[:3, 3] = R, -R @ eye
    return view.float()


def demo_scene(n: int, device: str, seed: int = 0):
    """A textured ground disc and a few coloured blobs: the Gaussians' parameters as torch tensors."""
    g = torch.Generator().manual_seed(seed)
    ground = n // 2
    r = torch.sqrt(torch.rand(ground, generator=g)) * 2.5
    a = torch.rand(ground, generator=g) * 2 * math.pi
    ground_means = torch.stack([r * torch.cos(a), torch.full_like(r, 0.5), r * torch.sin(a)], -1)
    checker = ((torch.floor(ground_means[:, 0] * 2) + torch.floor(ground_means[:, 2] * 2)) % 2)[:, None]
    ground_colors = checker * torch.tensor([0.2, 0.5, 0.15]) + (1 - checker) * torch.tensor([0.45, 0.35, 0.2])
    blobs = n - ground
    centers = torch.tensor([[0.0, -0.2, 0.0], [1.2, 0.0, 0.6], [-1.0, 0.1, -0.7]])
    which = torch.randint(0, 3, (blobs,), generator=g)
    blob_means = centers[which] + torch.randn(blobs, 3, generator=g) * 0.25
    blob_colors = torch.tensor([[0.9, 0.2, 0.2], [0.2, 0.3, 0.9], [0.95, 0.85, 0.2]])[which]
    means = torch.cat([ground_means, blob_means])
    colors = torch.cat([ground_colors, blob_colors]).clamp(0, 1)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.2 + math.log(0.05))
    scales[:ground, 1] = 0.005  # flat splats on the ground
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    opacities = torch.full((n,), 0.8)
    sh = ((colors - 0.5) / 0.28209479177387814)[:, None, :]
    return {k: v.to(device) for k, v in dict(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh).items()}


def save_png(path: str, image: torch.Tensor) -> None:
    from PIL import Image

    Image.fromarray((image.detach().clamp(0, 1).cpu().numpy() * 255).astype(np.uint8)).save(path)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=None, help="garden scene folder (used once the trainer exists)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument("--out", default="outputs/garden_demo", help="output folder")
    parser.add_argument("--gaussians", type=int, default=20000, help="number of Gaussians in the demo scene")
    parser.add_argument("--views", type=int, default=8, help="orbit views to render")
    parser.add_argument("--steps", type=int, default=50, help="gradient steps on the colours")
    args = parser.parse_args()
    if args.gaussians <= 0 or args.views <= 0 or args.steps < 0:
        parser.error("--gaussians and --views must be positive and --steps non-negative")
    print("cdcgs: the trainer is not implemented yet; rendering and fitting a procedural demo scene instead.")
    os.makedirs(args.out, exist_ok=True)
    width, height = 320, 208
    K = torch.tensor([[280.0, 0.0, width / 2], [0.0, 280.0, height / 2], [0.0, 0.0, 1.0]])
    scene = demo_scene(args.gaussians, args.device)
    start = time.perf_counter()
    images = []
    for v in range(args.views):
        image, _, info = cdcgs.rasterize(
            **scene, viewmat=orbit_viewmat(2 * math.pi * v / args.views), K=K, width=width, height=height,
            background=[1.0, 1.0, 1.0],
        )  # fmt: skip
        images.append(image)
        save_png(os.path.join(args.out, f"view_{v:02d}.png"), image)
    render_s = time.perf_counter() - start
    print(f"rendered {args.views} views of {args.gaussians} Gaussians at {width}x{height} on {args.device} in {render_s:.2f} s")

    # Recover the colours of view 0 from a grey start: gradients flow through the Warp kernels.
    target = images[0].detach()
    sh = torch.zeros_like(scene["sh"]).requires_grad_()
    optimizer = torch.optim.Adam([sh], lr=0.05)
    view0 = orbit_viewmat(0.0)
    for step in range(args.steps + 1):
        image, _, _ = cdcgs.rasterize(
            scene["means"], scene["quats"], scene["scales"], scene["opacities"], sh, viewmat=view0, K=K,
            width=width, height=height, background=[1.0, 1.0, 1.0],
        )  # fmt: skip
        mse = ((image - target) ** 2).mean()
        if step == 0 or step == args.steps:
            print(f"step {step:3d}: PSNR to view 0 {-10 * math.log10(max(mse.item(), 1e-12)):.2f} dB")
        if step < args.steps:
            optimizer.zero_grad()
            mse.backward()
            optimizer.step()
    save_png(os.path.join(args.out, "fitted_view_00.png"), image)
    print(f"outputs in {os.path.abspath(args.out)}")


if __name__ == "__main__":
    main()
