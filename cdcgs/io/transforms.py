"""NeRF-style ``transforms.json`` scenes (instant-ngp, nerfstudio, Blender synthetic).

Camera-to-world matrices in the OpenGL convention (x right, y up, z backwards) are converted once
to world-to-camera matrices in ours (x right, y down, z forward). Intrinsics are shared at the top
level or given per frame (``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h``, or ``camera_angle_x``);
``k1 k2 p1 p2`` (and ``k3``) distortion is undistorted to pinhole by pycolmap, like COLMAP's.
"""

from __future__ import annotations

import json
import logging
import math
import os

import numpy as np
import torch
from PIL import Image

from ..errors import InputError
from ._pycolmap import import_pycolmap
from .views import View, check_intrinsics, random_points_in_frustums, report_missing

__all__ = ["read_transforms"]

log = logging.getLogger("cdcgs")

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
INTRINSIC_KEYS = (
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "camera_angle_x",
    "camera_angle_y",
    "k1",
    "k2",
    "k3",
    "p1",
    "p2",
)
IMAGE_SUFFIXES = ("", ".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


def _number(json_path, where: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(json_path, f"{where}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def _resolve_image(base: str, file_path: str) -> str | None:
    candidate = os.path.normpath(os.path.join(base, file_path))
    for suffix in IMAGE_SUFFIXES:
        if os.path.isfile(candidate + suffix):
            return candidate + suffix
    return None


def _pose(json_path, where: str, matrix) -> torch.Tensor:
    try:
        c2w = np.array(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(json_path, f"{where}: transform_matrix is not a 4x4 matrix of numbers") from None
    if c2w.shape == (3, 4):
        c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
    if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
        raise InputError(
            json_path, f"{where}: transform_matrix must be a finite 4x4 (or 3x4) matrix, got shape {c2w.shape}"
        )
    rotation = c2w[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0:
        raise InputError(
            json_path,
            f"{where}: transform_matrix's rotation is not orthonormal (scaled or mirrored poses are not supported)",
        )
    c2w = c2w @ OPENGL_TO_OPENCV
    w2c = np.eye(4)
    w2c[:3, :3] = c2w[:3, :3].T
    w2c[:3, 3] = -c2w[:3, :3].T @ c2w[:3, 3]
    return torch.from_numpy(w2c).float()


def _read_point_cloud(json_path: str, ply_path: str):
    from plyfile import PlyData

    try:
        vertex = PlyData.read(ply_path)["vertex"]
        points = np.stack([vertex["x"], vertex["y"], vertex["z"]], -1).astype(np.float32)
    except (OSError, KeyError, ValueError, IndexError) as err:
        raise InputError(
            ply_path, f"cannot read the initial point cloud named by {os.path.basename(json_path)}: {err}"
        ) from None
    names = vertex.data.dtype.names
    if all(c in names for c in ("red", "green", "blue")):
        colors = np.stack([vertex["red"], vertex["green"], vertex["blue"]], -1).astype(np.uint8)
    else:
        colors = np.full((len(points), 3), 128, np.uint8)
    if not np.isfinite(points).all() or len(points) == 0:
        raise InputError(ply_path, "the initial point cloud is empty or has non-finite coordinates")
    return torch.from_numpy(points), torch.from_numpy(colors)


def read_transforms(json_path: str, factor: int = 1, skip_missing: bool = False):
    """Views, initial points [P, 3] float32, colours [P, 3] uint8 and notes of a transforms.json scene."""
    pycolmap = import_pycolmap()

    base = os.path.dirname(os.path.abspath(json_path))
    try:
        with open(json_path) as f:
            meta = json.load(f)
    except OSError as err:
        raise InputError(json_path, f"cannot open: {err.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(json_path, f"malformed JSON: {err}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise InputError(json_path, "expected an object with a non-empty 'frames' list")
    shared = {k: meta[k] for k in INTRINSIC_KEYS if k in meta}
    views, missing, notes = [], [], []
    for i, frame in enumerate(meta["frames"]):
        where = f"frame {i}"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise InputError(json_path, f"{where}: needs a 'file_path' string")
        if "transform_matrix" not in frame:
            raise InputError(json_path, f"{where} ({frame['file_path']}): needs a 'transform_matrix'")
        image_path = _resolve_image(base, frame["file_path"])
        if image_path is None:
            missing.append(frame["file_path"])
            continue
        params = {**shared, **{k: frame[k] for k in INTRINSIC_KEYS if k in frame}}
        params = {k: _number(json_path, where, k, v) for k, v in params.items()}
        try:
            with Image.open(image_path) as im:
                file_size = im.size
        except OSError as err:
            raise InputError(image_path, f"cannot read the image: {err}") from None
        width, height = int(params.get("w", file_size[0])), int(params.get("h", file_size[1]))
        if (width, height) != file_size:
            raise InputError(
                image_path,
                f"image is {file_size[0]}x{file_size[1]} but {os.path.basename(json_path)} says {width}x{height}",
            )
        if "fl_x" in params:
            fx = params["fl_x"]
        elif "camera_angle_x" in params:
            fx = 0.5 * width / math.tan(0.5 * params["camera_angle_x"])
        else:
            raise InputError(json_path, f"{where}: no focal length (fl_x or camera_angle_x)")
        if "fl_y" in params:
            fy = params["fl_y"]
        elif "camera_angle_y" in params:
            fy = 0.5 * height / math.tan(0.5 * params["camera_angle_y"])
        else:
            fy = fx
        if fx <= 0 or fy <= 0:
            raise InputError(json_path, f"{where}: focal lengths must be positive, got {fx}, {fy}")
        cx, cy = params.get("cx", width / 2), params.get("cy", height / 2)
        distortion = [params.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")]
        undistort = None
        if any(distortion):
            k1, k2, p1, p2, k3 = distortion
            model, extra = ("FULL_OPENCV", [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]) if k3 else ("OPENCV", [k1, k2, p1, p2])
            camera = pycolmap.Camera(model=model, width=width, height=height, params=[fx, fy, cx, cy, *extra])
            pinhole = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)
            width, height = pinhole.width, pinhole.height
            fx, fy, cx, cy = pinhole.params
            undistort = camera
        sx = sy = 1.0
        resize_from = None
        if factor > 1 or undistort is not None:
            new_w, new_h = max(1, round(width / factor)), max(1, round(height / factor))
            sx, sy = new_w / width, new_h / height
            width, height, resize_from = new_w, new_h, image_path
        check_intrinsics(json_path, where, fx * sx, fy * sy, cx * sx, cy * sy, width, height)
        K = torch.tensor([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]], dtype=torch.float32)
        views.append(
            View(
                name=os.path.relpath(image_path, base),
                image_path=image_path,
                width=width,
                height=height,
                K=K,
                viewmat=_pose(json_path, where, frame["transform_matrix"]),
                resize_from=resize_from,
                undistort_camera=undistort,
            )
        )
    if missing:
        message = f"{len(missing)} of {len(meta['frames'])} frames have no image file, first {missing[:5]}"
        report_missing(json_path, message, skip_missing, notes)
    if not views:
        raise InputError(json_path, "no frame has an image")
    if "ply_file_path" in meta:
        if not isinstance(meta["ply_file_path"], str):
            raise InputError(json_path, "'ply_file_path' must be a string")
        points, colors = _read_point_cloud(json_path, os.path.join(base, meta["ply_file_path"]))
    else:
        points, colors = random_points_in_frustums(views)
        note = "no ply_file_path: random initial points inside the cameras' common view (as 3DGS does for such scenes)"
        log.warning("%s: %s", json_path, note)
        notes.append(note)
    return views, points, colors, notes
