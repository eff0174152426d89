"""Render Gaussians with cdcgs's Warp kernels alone: plain ``wp.launch`` on Warp arrays, no torch.

This is how a simulator that already holds its state in Warp arrays embeds the rasterizer.
Run: python examples/warp_launch.py [--device cpu|cuda] [--out image.png]
"""

import argparse

import numpy as np
import warp as wp

from cdcgs.kernels import (
    BLOCK_SIZE,
    bin_gaussians,
    blend_forward_kernel,
    make_camera,
    project_gaussians_kernel,
    sh_to_color_kernel,
)


def render(means, quats, scales, opacities, sh, viewmat, K, width, height, device="cpu"):
    """Numpy in ([N,3], [N,4] wxyz, [N,3], [N], [N,K,3], [4,4], [3,3]), numpy image [H, W, 3] out."""
    n = len(means)
    camera = make_camera(viewmat, K, width, height)
    means_wp = wp.array(means, dtype=wp.vec3, device=device)
    # The projection writes every entry (zeros and radius 0 for culled Gaussians).
    means2d = wp.empty(n, dtype=wp.vec2, device=device)
    conics = wp.empty(n, dtype=wp.vec3, device=device)
    depths = wp.empty(n, dtype=float, device=device)
    composited_opacities = wp.empty(n, dtype=float, device=device)
    radii = wp.empty(n, dtype=wp.vec2i, device=device)
    wp.launch(
        project_gaussians_kernel,
        dim=n,
        inputs=[
            means_wp,
            wp.array(quats, dtype=wp.vec4, device=device),
            wp.array(scales, dtype=wp.vec3, device=device),
            wp.array(opacities, dtype=float, device=device),
            camera,
            None,  # the camera is `camera` (a trainer replaying a CUDA graph passes an array it writes)
            0,  # antialiased
        ],
        outputs=[means2d, conics, depths, composited_opacities, radii, None],  # None: no finiteness flags
        device=device,
    )
    colors = wp.zeros(n, dtype=wp.vec3, device=device)
    sh_degree = int(np.sqrt(sh.shape[1])) - 1
    wp.launch(
        sh_to_color_kernel,
        dim=n,
        # None: every coefficient in the one [N, K] array (a trainer may pass degree 0 and the rest apart)
        inputs=[means_wp, wp.array(sh, dtype=wp.vec3, device=device), None, sh_degree, camera.center, None, radii],
        outputs=[colors, None],  # None: no finiteness flag
        device=device,
    )
    # With the conics and opacities each Gaussian goes only into the tiles its footprint reaches
    # (without them, into its whole bounding rectangle: the same image, more work).
    bins = bin_gaussians(means2d, radii, depths, width, height, conics=conics, opacities=composited_opacities)
    image = wp.zeros((height, width), dtype=wp.vec3, device=device)
    transmittance = wp.zeros((height, width), dtype=float, device=device)
    depth_sum = wp.zeros((height, width), dtype=float, device=device)
    last_contributor = wp.zeros((height, width), dtype=wp.int32, device=device)
    background = wp.array([wp.vec3(1.0, 1.0, 1.0)], dtype=wp.vec3, device=device)
    wp.launch(
        blend_forward_kernel,
        dim=bins.tiles_x * bins.tiles_y * BLOCK_SIZE,  # one thread per pixel of every tile
        inputs=[
            bins.tile_ranges,  # [tiles_y * tiles_x, 2]: [start, end) of each tile's list
            bins.sorted_gauss_ids,
            means2d,
            conics,
            colors,
            composited_opacities,
            depths,
            background,
            width,
            height,
            bins.tiles_x,
            0,  # chunk_size: no checkpoints for a chunked adjoint (the three None outputs below)
        ],
        outputs=[image, transmittance, depth_sum, last_contributor, None, None, None],
        block_dim=BLOCK_SIZE,  # one tile per block
        device=device,
    )
    return image.numpy()


def demo_scene(n=2000, seed=0):
    """A ring of coloured Gaussians around the origin, seen from 4 units away."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    means = np.stack([np.cos(angle), 0.3 * rng.normal(size=n), np.sin(angle)], -1).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    scales = np.exp(rng.normal(np.log(0.04), 0.3, size=(n, 3))).astype(np.float32)
    opacities = rng.uniform(0.3, 0.9, n).astype(np.float32)
    sh = np.zeros((n, 1, 3), np.float32)
    sh[:, 0] = (np.stack([np.cos(angle), np.sin(angle), np.cos(2 * angle)], -1) * 0.5 / 0.2820948).astype(np.float32)
    viewmat = np.eye(4, dtype=np.float32)
    viewmat[:3, 3] = [0.0, 0.0, 4.0]
    K = np.array([[120.0, 0, 96.0], [0, 120.0, 64.0], [0, 0, 1]], np.float32)
    return means, quats, scales, opacities, sh, viewmat, K, 192, 128


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if wp.is_cuda_available() else "cpu", help="Warp device")
    parser.add_argument("--out", default="warp_launch.png", help="where to write the PNG")
    args = parser.parse_args()
    image = render(*demo_scene(), device=args.device)
    from PIL import Image

    Image.fromarray((np.clip(image, 0, 1) * 255).astype(np.uint8)).save(args.out)
    print(f"wrote {args.out} ({image.shape[1]}x{image.shape[0]}, device {args.device})")


if __name__ == "__main__":
    main()
