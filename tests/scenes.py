"""Small synthetic scenes on disk (COLMAP models built with pycolmap, transforms.json files),
with images drawn from known patterns, for the I/O tests."""

import json
import math
import os

import numpy as np
import torch
from PIL import Image


def look_at_w2c(eye, target=(0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera 4x4 (x right, y down, z forward) of a camera at eye looking at target."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
    return w2c


def orbit_poses(n: int, radius: float = 4.0, height: float = -1.0) -> list[np.ndarray]:
    return [
        look_at_w2c((radius * math.sin(a), height, -radius * math.cos(a)))
        for a in np.linspace(0, 2 * math.pi, n, endpoint=False)
    ]


def pattern_image(width: int, height: int, seed: int) -> np.ndarray:
    """A deterministic colourful pattern, different per seed."""
    y, x = np.mgrid[0:height, 0:width]
    r = (np.sin(x * 0.3 + seed) * 0.5 + 0.5) * 255
    g = (np.cos(y * 0.25 + 2 * seed) * 0.5 + 0.5) * 255
    b = ((x + y + 7 * seed) % 32) * 8
    return np.stack([r, g, b], -1).astype(np.uint8)


def distort(x, y, k1, k2, p1, p2):
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def undistort_points(xd, yd, k1, k2, p1, p2, iterations=50):
    """Invert the distortion by OpenCV's fixed-point iteration x = (x_d - tangential) / radial."""
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
    return x, y


def distorted_line_image(width, height, fx, fy, cx, cy, dist, line=(0.15, 1.0, -0.4), thickness=0.006):
    """The distorted picture of the straight line a*x + b*y + c = 0 in normalised pinhole coordinates."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    xd, yd = (u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy
    x, y = undistort_points(xd, yd, *dist)
    a, b, c = line
    on_line = np.abs(a * x + b * y + c) / math.hypot(a, b) < thickness
    image = np.full((height, width, 3), 20, np.uint8)
    image[on_line] = 255
    return image


def write_colmap_scene(
    root,
    *,
    n_images=10,
    width=64,
    height=48,
    model="PINHOLE",
    params=None,
    factors=(),
    text=False,
    points=None,
    with_images=True,
):
    """A COLMAP scene under root: sparse/0 (binary or text), images/ and images_{f} for f in factors.

    Returns (reconstruction, poses, params).
    """
    import pycolmap

    params = params or {"PINHOLE": [50.0, 52.0, 31.5, 24.2], "SIMPLE_PINHOLE": [51.0, 32.3, 23.6]}.get(model)
    camera = pycolmap.Camera(model=model, width=width, height=height, params=params, camera_id=1)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(camera)
    poses = orbit_poses(n_images)
    for i, w2c in enumerate(poses):
        image = pycolmap.Image(name=f"img_{i:03d}.png", camera_id=1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_image_with_trivial_frame(image, pose)
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 0.5, (50, 3)) if points is None else points
    for p in pts:
        rec.add_point3D(np.asarray(p, dtype=np.float64), pycolmap.Track(), rng.integers(0, 255, 3).astype(np.uint8))
    model_dir = os.path.join(root, "sparse", "0")
    os.makedirs(model_dir, exist_ok=True)
    (rec.write_text if text else rec.write)(model_dir)
    if with_images:
        for folder, f in [("images", 1)] + [(f"images_{f}", f) for f in factors]:
            os.makedirs(os.path.join(root, folder), exist_ok=True)
            for i in range(n_images):
                w, h = round(width / f), round(height / f)
                Image.fromarray(pattern_image(w, h, i)).save(os.path.join(root, folder, f"img_{i:03d}.png"))
    return rec, poses, params


def write_transforms_scene(
    root, *, n_images=10, width=40, height=30, per_frame=False, angle=False, extra=None, ply=None
):
    """A transforms.json scene (OpenGL camera-to-world) under root. Returns (meta, w2c poses)."""
    os.makedirs(os.path.join(root, "images"), exist_ok=True)
    poses = orbit_poses(n_images, radius=3.0)
    opengl = np.diag([1.0, -1.0, -1.0, 1.0])
    frames = []
    for i, w2c in enumerate(poses):
        c2w_gl = np.linalg.inv(w2c) @ opengl
        frame = {"file_path": f"images/frame_{i:03d}", "transform_matrix": c2w_gl.tolist()}
        if per_frame:
            frame.update(fl_x=40.0 + i, fl_y=41.0 + i, cx=19.5, cy=15.25, w=width, h=height)
        frames.append(frame)
        Image.fromarray(pattern_image(width, height, i)).save(os.path.join(root, "images", f"frame_{i:03d}.png"))
    meta = {"frames": frames}
    if not per_frame:
        meta.update(
            {"camera_angle_x": 1.2}
            if angle
            else {"fl_x": 45.0, "fl_y": 46.0, "cx": 20.5, "cy": 14.0, "w": width, "h": height}
        )
    if ply is not None:
        meta["ply_file_path"] = ply
    meta.update(extra or {})
    with open(os.path.join(root, "transforms.json"), "w") as f:
        json.dump(meta, f)
    return meta, poses


def project(view, X):
    """Pixel of world point X through the loaded view (our convention)."""
    cam = view.viewmat[:3, :3].double() @ torch.as_tensor(X, dtype=torch.float64) + view.viewmat[:3, 3].double()
    K = view.K.double()
    return np.array([(K[0, 0] * cam[0] / cam[2] + K[0, 2]).item(), (K[1, 1] * cam[1] / cam[2] + K[1, 2]).item()])


def line_residual(mask: np.ndarray) -> float:
    """RMS distance (px) of the mask's pixels from their best-fit straight line."""
    ys, xs = np.nonzero(mask)
    pts = np.stack([xs, ys], 1).astype(np.float64)
    pts -= pts.mean(0)
    return float(np.sqrt(np.linalg.svd(pts, compute_uv=False)[-1] ** 2 / len(pts)))


def _value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth pseudo-random texture in [0, 1]: bilinear value noise over four octaves."""
    total = np.zeros_like(u)
    for octave, weight in enumerate((0.4, 0.3, 0.2, 0.1)):
        scale = 6.0 * 2**octave
        x, y = u * scale, v * scale
        ix, iy = np.floor(x), np.floor(y)
        fx, fy = x - ix, y - iy
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)

        def lattice(a, b, octave=octave):
            h = a.astype(np.int64) * 374761393 + b.astype(np.int64) * 668265263 + (seed * 31 + octave) * 2654435761
            h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
            return (h & 0xFFFF) / 65535.0

        top = lattice(ix, iy) * (1 - fx) + lattice(ix + 1, iy) * fx
        bottom = lattice(ix, iy + 1) * (1 - fx) + lattice(ix + 1, iy + 1) * fx
        total += weight * (top * (1 - fy) + bottom * fy)
    return total


def textured_room_views(count: int, width: int, height: int, radius: float = 2.0):
    """Pictures from inside a box room (half-size 3) whose six faces carry smooth noise textures,
    from ``count`` cameras on a wavy circle looking at the centre: a scene every view of which
    SIFT can match. Returns (images [count] of uint8 [H, W, 3], w2c poses [count] 4 x 4,
    intrinsics (fx, fy, cx, cy)); COLMAP's camera convention (x right, y down, z forward)."""
    half = 3.0
    f = 0.8 * width
    intrinsics = (f, f, width / 2, height / 2)
    v, u = np.mgrid[0:height, 0:width]
    cam_dirs = np.stack([(u + 0.5 - width / 2) / f, (v + 0.5 - height / 2) / f, np.ones_like(u, dtype=float)], -1)
    cam_dirs = cam_dirs.reshape(-1, 3)
    images, poses = [], []
    for i in range(count):
        angle = 2 * np.pi * i / count
        eye = np.array([radius * np.sin(angle), 0.3 * np.sin(2 * angle), radius * np.cos(angle)])
        target = np.array([0.0, 0.0, 0.0]) - 0.5 * eye  # look past the centre, tilted a little
        forward = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(forward, [0.0, -1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        dirs = cam_dirs @ R
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            bounds = np.where(dirs > 0, half, -half)
            t = (bounds - eye) / dirs
        t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
        axis = t.argmin(-1)
        hit = eye + dirs * t.min(-1, keepdims=True)
        color = np.zeros((len(dirs), 3))
        for a in range(3):
            for sign in (-1, 1):
                mask = (axis == a) & (np.sign(dirs[:, a]) == sign)
                if not mask.any():
                    continue
                p, q = [k for k in range(3) if k != a]
                face = a * 2 + (sign > 0)
                uu, vv = hit[mask, p] / (2 * half) + 0.5, hit[mask, q] / (2 * half) + 0.5
                base = np.array([0.35 + 0.1 * (face % 3), 0.3 + 0.08 * face, 0.55 - 0.07 * face])
                shade = np.clip((_value_noise(uu, vv, face) - 0.5) * 3.0 + 0.5, 0, 1)[:, None]
                # Dark and light dots, one per cell of a 24 x 24 grid: blobs at every scale SIFT sees.
                cu, cv = np.floor(uu * 24), np.floor(vv * 24)
                jitter = _value_noise(cu * 7.1, cv * 3.3, face + 10)
                du, dv = uu * 24 - cu - 0.3 - 0.4 * jitter, vv * 24 - cv - 0.7 + 0.4 * jitter
                dot = (du * du + dv * dv < 0.06)[:, None]
                ink = (jitter > 0.5)[:, None].astype(float)
                color[mask] = np.where(dot, ink, np.clip(base * 0.5 + shade * 0.7 - 0.1, 0, 1))
        images.append((color.reshape(height, width, 3) * 255 + 0.5).astype(np.uint8))
        poses.append(w2c)
    return images, poses, intrinsics
