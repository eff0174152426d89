"""A procedural garden-like scene, rendered by an independent ray caster and written as COLMAP.

It is the default scene of ``examples/train_garden.py`` when the MipNeRF-360 garden is absent:
a textured ground, a flat wall, a few objects with fine texture, a smooth sky dome, seen from an
orbit of cameras. The pictures come from analytic ray-surface intersections with 3x3
supersampling, not from the Gaussian rasterizer, so training on them tests the rasterizer
against an independent image formation. World y is up; the COLMAP cameras follow COLMAP's
convention (x right, y down, z forward).
"""

from __future__ import annotations

import math
import os

import numpy as np
from PIL import Image

from ..io._pycolmap import import_pycolmap

__all__ = ["make_procedural_scene", "orbit_cameras", "render", "sparse_points", "trace"]

LIGHT = np.array([0.4, 0.8, 0.45]) / np.linalg.norm([0.4, 0.8, 0.45])
LOOK_AT = np.array([0.0, 0.4, 0.0])
DOME_RADIUS = 7.0
WALL_Z = -1.9
GROUND_HALF = 3.2


def _hash_noise(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) per integer lattice cell."""
    h = (ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263 + seed * 2147483647) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    return (h & 0xFFFF) / 65536.0


def _ground_color(p):
    x, z = p[:, 0], p[:, 2]
    checker = ((np.floor(x * 5) + np.floor(z * 5)) % 2)[:, None]
    noise = _hash_noise(np.floor(x * 12), np.floor(z * 12), 1)[:, None]
    return np.array([0.22, 0.45, 0.16]) * (0.75 + 0.35 * noise) + checker * np.array([0.12, 0.08, 0.02])


def _wall_color(p):
    return np.tile(np.array([0.78, 0.74, 0.66]), (len(p), 1))  # flat: no texture at all


def _striped_sphere_color(p, center):
    d = p - center
    stripes = (np.sin(d[:, 1] * 40 + np.arctan2(d[:, 2], d[:, 0]) * 3) > 0)[:, None]
    return np.where(stripes, np.array([0.85, 0.2, 0.15]), np.array([0.95, 0.85, 0.35]))


def _spotted_sphere_color(p, center):
    d = p - center
    cells = _hash_noise(np.floor((d[:, 0] + 2) * 14), np.floor((d[:, 1] * 0.7 + d[:, 2] + 2) * 14), 7)[:, None]
    return np.array([0.15, 0.25, 0.75]) * (0.6 + 0.8 * cells)


def _box_color(p):
    checker = ((np.floor(p[:, 0] * 10) + np.floor(p[:, 1] * 10) + np.floor(p[:, 2] * 10)) % 2)[:, None]
    return np.where(checker > 0, np.array([0.9, 0.9, 0.9]), np.array([0.1, 0.1, 0.12]))


def _sky_color(d):
    up = np.clip(d[:, 1:2], -1, 1)
    return np.array([0.75, 0.85, 0.95]) * (1 - up) * 0.6 + np.array([0.35, 0.55, 0.9]) * (0.4 + 0.6 * up)


SPHERES = [  # centre, radius, colour function
    (np.array([0.0, 0.45, 0.0]), 0.45, _striped_sphere_color),
    (np.array([-1.05, 0.3, 0.55]), 0.3, _spotted_sphere_color),
]
BOX = (np.array([0.75, 0.0, 0.25]), np.array([1.35, 0.6, 0.85]))


def _sphere_hit(o, d, center, radius):
    oc = o - center
    b = (oc * d).sum(-1)
    c = (oc * oc).sum(-1) - radius * radius
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0))
    return np.where((disc > 0) & (t > 1e-4), t, np.inf)


def _box_hit(o, d, lo, hi):
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((tmax >= tmin) & (tmin > 1e-4), tmin, np.inf)


def _plane_hit(o, d, axis, value, bounds):
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (value - o[:, axis]) / d[:, axis]
    p = o + t[:, None] * d
    inside = np.ones(len(o), bool)
    for ax, (lo, hi) in bounds.items():
        inside &= (p[:, ax] >= lo) & (p[:, ax] <= hi)
    return np.where(inside & (t > 1e-4), t, np.inf)


def trace(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour [R, 3], hit points [R, 3] and surface id [R] of rays (unit directions)."""
    hits = [
        _plane_hit(origins, dirs, 1, 0.0, {0: (-GROUND_HALF, GROUND_HALF), 2: (-GROUND_HALF, GROUND_HALF)}),
        _plane_hit(origins, dirs, 2, WALL_Z, {0: (-2.6, 2.6), 1: (0.0, 2.2)}),
        _sphere_hit(origins, dirs, SPHERES[0][0], SPHERES[0][1]),
        _sphere_hit(origins, dirs, SPHERES[1][0], SPHERES[1][1]),
        _box_hit(origins, dirs, *BOX),
    ]
    t = np.stack(hits, -1)
    surface = np.argmin(t, -1)
    t_hit = t[np.arange(len(t)), surface]
    sky = ~np.isfinite(t_hit)
    oc = origins
    b = (oc * dirs).sum(-1)
    t_dome = -b + np.sqrt(np.maximum(b * b - (oc * oc).sum(-1) + DOME_RADIUS**2, 0))
    t_hit = np.where(sky, t_dome, t_hit)
    surface = np.where(sky, len(hits), surface)
    p = origins + t_hit[:, None] * dirs
    color = np.zeros_like(p)
    normal = np.zeros_like(p)
    masks = [surface == i for i in range(len(hits) + 1)]
    color[masks[0]], normal[masks[0]] = _ground_color(p[masks[0]]), [0, 1, 0]
    color[masks[1]], normal[masks[1]] = _wall_color(p[masks[1]]), [0, 0, 1]
    for k, (center, radius, fn) in enumerate(SPHERES):
        m = masks[2 + k]
        color[m] = fn(p[m], center)
        normal[m] = (p[m] - center) / radius
    m = masks[4]
    color[m] = _box_color(p[m])
    lo, hi = BOX
    rel = (p[m] - (lo + hi) / 2) / ((hi - lo) / 2)
    axis = np.argmax(np.abs(rel), -1)
    box_normal = np.zeros_like(rel)
    box_normal[np.arange(len(rel)), axis] = np.sign(rel[np.arange(len(rel)), axis])
    normal[m] = box_normal
    shade = 0.45 + 0.55 * np.clip((normal * LIGHT).sum(-1, keepdims=True), 0, 1)
    color = np.where(masks[5][:, None], _sky_color(p / DOME_RADIUS), color * shade)
    return np.clip(color, 0, 1), p, surface


def orbit_cameras(count: int, width: int, height: int, radius: float = 3.3):
    """World-to-camera matrices on a wavy orbit around the scene and the shared intrinsics."""
    poses = []
    for i in range(count):
        angle = 2 * math.pi * i / count
        eye = np.array([radius * math.sin(angle), 1.1 + 0.35 * math.sin(3 * angle), radius * math.cos(angle)])
        forward = LOOK_AT - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R = np.stack([right, down, forward])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        poses.append(w2c)
    f = 0.95 * width
    return poses, (f, f, width / 2, height / 2)


def render(w2c: np.ndarray, intrinsics, width: int, height: int, supersample: int = 3) -> np.ndarray:
    """[H, W, 3] uint8 picture of the scene through a pinhole camera (pixel centres at +0.5)."""
    fx, fy, cx, cy = intrinsics
    s = supersample
    offsets = (np.arange(s) + 0.5) / s
    v, u = np.mgrid[0:height, 0:width]
    u, v = np.broadcast_arrays(
        u[..., None, None] + offsets[None, None, None, :], v[..., None, None] + offsets[None, None, :, None]
    )
    u, v = u.reshape(-1), v.reshape(-1)
    cam_dirs = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    R, t = w2c[:3, :3], w2c[:3, 3]
    dirs = cam_dirs @ R  # R^T d
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origin = -R.T @ t
    color, _, _ = trace(np.broadcast_to(origin, dirs.shape).copy(), dirs)
    image = color.reshape(height, width, s * s, 3).mean(2)
    return (image * 255 + 0.5).astype(np.uint8)


def sparse_points(poses, intrinsics, width, height, count: int = 6000, seed: int = 0):
    """A sparse 'SfM' point cloud: surface points seen through the cameras, with their colours."""
    rng = np.random.default_rng(seed)
    fx, fy, cx, cy = intrinsics
    points, colors = [], []
    for w2c in poses[::2]:
        u = rng.uniform(0, width, 400)
        v = rng.uniform(0, height, 400)
        d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1) @ w2c[:3, :3]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        origin = -w2c[:3, :3].T @ w2c[:3, 3]
        color, p, _ = trace(np.broadcast_to(origin, d.shape).copy(), d)
        points.append(p)
        colors.append(color)
    points, colors = np.concatenate(points), np.concatenate(colors)
    keep = rng.permutation(len(points))[:count]
    jitter = rng.normal(0, 0.01, (len(keep), 3))
    return points[keep] + jitter, (colors[keep] * 255).astype(np.uint8)


def make_procedural_scene(
    root, *, views: int = 40, width: int = 96, height: int = 72, points: int = 6000, seed: int = 0
) -> str:
    """Write the scene to ``root`` as a COLMAP folder (sparse/0, images/); returns ``root``."""
    pycolmap = import_pycolmap()  # after PIL (see cdcgs/io/colmap.py)

    root = os.fspath(root)
    poses, intrinsics = orbit_cameras(views, width, height)
    os.makedirs(os.path.join(root, "images"), exist_ok=True)
    reconstruction = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="PINHOLE", width=width, height=height, params=list(intrinsics), camera_id=1)
    reconstruction.add_camera_with_trivial_rig(camera)
    for i, w2c in enumerate(poses):
        name = f"view_{i:03d}.png"
        Image.fromarray(render(w2c, intrinsics, width, height)).save(os.path.join(root, "images", name))
        image = pycolmap.Image(name=name, camera_id=1, image_id=i + 1)
        reconstruction.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        )
    cloud, colors = sparse_points(poses, intrinsics, width, height, count=points, seed=seed)
    for p, c in zip(cloud, colors):
        reconstruction.add_point3D(p, pycolmap.Track(), c)
    model_dir = os.path.join(root, "sparse", "0")
    os.makedirs(model_dir, exist_ok=True)
    reconstruction.write(model_dir)
    return root
