"""COLMAP scenes (the MipNeRF-360 layout: images/, images_2/, ..., sparse/0/) through pycolmap.

PINHOLE and SIMPLE_PINHOLE cameras are used directly. Any other model is undistorted to pinhole
once by pycolmap and cached next to the scene (or in the user cache when the scene folder is
read-only); it is never treated as pinhole silently.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import tempfile

import numpy as np
import torch
from PIL import Image

from ..errors import InputError, OptionError
from ._pycolmap import import_pycolmap
from .views import View, check_intrinsics, random_points_in_frustums, report_missing

__all__ = ["check_model_files", "find_model_dir", "read_colmap", "read_reconstruction", "undistorted_scene"]

log = logging.getLogger("cdcgs")

# pycolmap is imported inside functions, so PIL (imported above) is always loaded first: with
# pycolmap's native libraries loaded before PIL's, PIL's PNG encoder can crash (a zlib clash seen
# with pycolmap 4.2.1 and Pillow 13).
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
CACHE_VERSION = 1


def find_model_dir(root: str) -> str:
    """``sparse/0`` or ``sparse`` under ``root``, whichever holds a COLMAP model."""
    for candidate in (os.path.join(root, "sparse", "0"), os.path.join(root, "sparse")):
        if any(os.path.isfile(os.path.join(candidate, f"cameras.{ext}")) for ext in ("bin", "txt")):
            return candidate
    suffixes = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
    for folder in (root, os.path.join(root, "images")):
        photos = [n for n in os.listdir(folder) if n.lower().endswith(suffixes)] if os.path.isdir(folder) else []
        if photos:
            raise InputError(
                root,
                f"holds {len(photos)} photos but no camera poses (no COLMAP model in sparse/0/): "
                f"make a scene with `cdcgs process {folder} --out SCENE` and train on SCENE",
            )
    raise InputError(root, "no COLMAP model: expected sparse/0/ or sparse/ holding cameras.bin or cameras.txt")


# Smallest record of each binary model file after its uint64 count (COLMAP's layout): a camera
# (id, model, width, height, one parameter), an image (id, qvec, tvec, camera id, a one-character
# name with its terminator, the uint64 count of its 2-D points), a 3-D point (id, xyz, rgb,
# error, the uint64 track length).
_MIN_RECORD = {
    "cameras.bin": 4 + 4 + 8 + 8 + 8,
    "images.bin": 4 + 32 + 24 + 4 + 2 + 8,
    "points3D.bin": 8 + 24 + 3 + 8 + 8,
}


def check_model_files(model_dir: str) -> int | None:
    """Check a COLMAP model's files before pycolmap reads them (a 0-byte points3D.bin cost 100 s
    and 17 GB inside pycolmap before it failed); the number of 3-D points for a binary model.

    Raises:
        InputError: naming a missing, empty or truncated file.
    """
    import struct

    binary = os.path.isfile(os.path.join(model_dir, "cameras.bin"))
    names = tuple(_MIN_RECORD) if binary else ("cameras.txt", "images.txt", "points3D.txt")
    points = None
    for name in names:
        path = os.path.join(model_dir, name)
        if not os.path.isfile(path):
            raise InputError(path, "missing: a COLMAP model needs cameras, images and points3D files")
        size = os.path.getsize(path)
        if size == 0:
            raise InputError(path, "is empty (0 bytes): not a COLMAP model file")
        if not binary:
            continue
        if size < 8:
            raise InputError(path, f"is truncated ({size} bytes, not even its record count)")
        with open(path, "rb") as f:
            (count,) = struct.unpack("<Q", f.read(8))
        if 8 + count * _MIN_RECORD[name] > size:
            raise InputError(
                path, f"is truncated or not a COLMAP file: it says it holds {count:,} records, but has {size:,} bytes"
            )
        if name == "points3D.bin":
            points = count
    return points


def read_reconstruction(model_dir: str):
    pycolmap = import_pycolmap()

    check_model_files(model_dir)
    try:
        return pycolmap.Reconstruction(model_dir)
    except Exception as err:  # pycolmap raises plain RuntimeError/ValueError on bad files
        raise InputError(model_dir, f"cannot read the COLMAP model: {err}") from None


def _folder_and_factor(root: str, images: str | None, factor: int | None) -> tuple[str, int]:
    if images is None:
        factor = factor or 1
        return ("images" if factor == 1 else f"images_{factor}"), factor
    match = re.fullmatch(r".*_(\d+)", images)
    implied = int(match.group(1)) if match else 1
    if factor is not None and factor != implied:
        raise OptionError(f"images={images!r} implies factor {implied}, but factor={factor} was given")
    return images, implied


def _pinhole_intrinsics(camera) -> tuple[float, float, float, float]:
    p = camera.params
    if camera.model.name == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2]
    return p[0], p[1], p[2], p[3]


def _fingerprint(model_dir: str, image_dir: str) -> str:
    parts = [str(CACHE_VERSION), os.path.abspath(image_dir)]
    for name in sorted(os.listdir(model_dir)):
        stat = os.stat(os.path.join(model_dir, name))
        parts.append(f"{name}:{stat.st_size}:{stat.st_mtime_ns}")
    return hashlib.sha256("|".join(parts).encode()).hexdigest()


def _writable(folder: str) -> bool:
    try:
        os.makedirs(folder, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, delete=True):
            return True
    except OSError:
        return False


def undistorted_scene(root: str, model_dir: str, reconstruction, image_dir: str) -> tuple[str, str]:
    """Undistort the images of ``image_dir`` to pinhole with pycolmap, once; returns (model, images).

    The cameras are first rescaled to the folder's image size. The result is cached in
    ``root/.cdcgs_cache/undistorted_<folder>`` (or ``~/.cache/cdcgs`` for read-only scenes) and
    rebuilt when the model files or the folder change.
    """
    pycolmap = import_pycolmap()

    folder_name = os.path.basename(os.path.normpath(image_dir))
    fingerprint = _fingerprint(model_dir, image_dir)
    cache = os.path.join(root, ".cdcgs_cache", f"undistorted_{folder_name}")
    if not _writable(os.path.dirname(cache)):
        user_cache = os.environ.get("XDG_CACHE_HOME", os.path.join(os.path.expanduser("~"), ".cache"))
        cache = os.path.join(
            user_cache,
            "cdcgs",
            hashlib.sha256(os.path.abspath(root).encode()).hexdigest()[:16],
            f"undistorted_{folder_name}",
        )
    marker = os.path.join(cache, "cdcgs_undistorted.json")
    if os.path.isfile(marker):
        with open(marker) as f:
            if json.load(f).get("fingerprint") == fingerprint:
                return os.path.join(cache, "sparse"), os.path.join(cache, "images")
    log.warning("undistorting %s to pinhole (once; cached in %s)", image_dir, cache)
    # Rescale each camera to the size of its images in this folder.
    for camera_id, camera in reconstruction.cameras.items():
        sample = next((img for img in reconstruction.images.values() if img.camera_id == camera_id), None)
        if sample is None:
            continue
        path = os.path.join(image_dir, sample.name)
        try:
            with Image.open(path) as im:
                width, height = im.size
        except OSError as err:
            raise InputError(path, f"cannot read the image: {err}") from None
        if (width, height) != (camera.width, camera.height):
            camera.rescale(width, height)
    if os.path.exists(cache):
        shutil.rmtree(cache)
    os.makedirs(cache)
    with tempfile.TemporaryDirectory() as scaled_model:
        reconstruction.write(scaled_model)
        try:
            pycolmap.undistort_images(cache, scaled_model, image_dir)
        except Exception as err:
            raise InputError(image_dir, f"pycolmap could not undistort the images: {err}") from None
    with open(marker, "w") as f:
        json.dump({"fingerprint": fingerprint, "source": os.path.abspath(image_dir)}, f)
    return os.path.join(cache, "sparse"), os.path.join(cache, "images")


def read_colmap(
    root: str,
    images: str | None = None,
    factor: int | None = None,
    skip_missing: bool = False,
    random_init: bool = False,
):
    """Views, initial points [P, 3] float32, their colours [P, 3] uint8 and notes of a COLMAP scene.

    A model without 3-D points is refused unless ``random_init``: then random points inside the
    cameras' common view, announced."""
    root = os.fspath(root)
    if not os.path.isdir(root):
        raise InputError(root, "no such scene folder")
    model_dir = find_model_dir(root)
    reconstruction = read_reconstruction(model_dir)
    folder_name, factor = _folder_and_factor(root, images, factor)
    image_dir = os.path.join(root, folder_name)
    notes = []
    resize_by = 1
    if not os.path.isdir(image_dir):
        full = os.path.join(root, "images")
        if factor > 1 and os.path.isdir(full):
            note = f"{image_dir} is missing: resizing the images of {full} by 1/{factor} on load"
            log.warning(note)
            notes.append(note)
            image_dir, resize_by = full, factor
        else:
            raise InputError(image_dir, "no such image folder")

    registered = sorted((img for img in reconstruction.images.values() if img.has_pose), key=lambda img: img.name)
    missing = [img.name for img in registered if not os.path.isfile(os.path.join(image_dir, img.name))]
    if missing:
        message = (
            f"{len(missing)} of {len(registered)} images of the model are missing from the folder, first {missing[:5]}"
        )
        report_missing(image_dir, message, skip_missing, notes)
        registered = [img for img in registered if img.name not in set(missing)]

    # Image sizes are read from the files before any undistortion, so that a folder of the wrong
    # size is reported as such rather than undistorted with the wrong camera.
    sizes = {}
    for img in registered:
        camera = reconstruction.cameras[img.camera_id]
        path = os.path.join(image_dir, img.name)
        try:
            with Image.open(path) as im:
                sizes[img.name] = im.size
        except OSError as err:
            raise InputError(path, f"cannot read the image: {err}") from None
        width, height = sizes[img.name]
        scale = factor // resize_by
        if abs(width * scale - camera.width) > scale or abs(height * scale - camera.height) > scale:
            raise InputError(
                path,
                f"image is {width}x{height} but its camera ({camera.width}x{camera.height}) at factor {scale} "
                f"expects about {camera.width / scale:.0f}x{camera.height / scale:.0f}",
            )

    if any(camera.model.name not in PINHOLE_MODELS for camera in reconstruction.cameras.values()):
        model_dir, image_dir = undistorted_scene(root, model_dir, reconstruction, image_dir)
        reconstruction = read_reconstruction(model_dir)
        notes.append(f"distorted cameras undistorted to pinhole, cached in {os.path.dirname(model_dir)}")
        by_name = {img.name: img for img in reconstruction.images.values()}
        registered = [by_name[img.name] for img in registered]
        sizes = {
            img.name: (
                reconstruction.cameras[img.camera_id].width * resize_by,
                reconstruction.cameras[img.camera_id].height * resize_by,
            )
            for img in registered
        }

    views = []
    for img in registered:
        camera = reconstruction.cameras[img.camera_id]
        width, height = sizes[img.name]
        if resize_by > 1:
            width, height = max(1, round(width / resize_by)), max(1, round(height / resize_by))
        fx, fy, cx, cy = _pinhole_intrinsics(camera)
        where = f"camera {img.camera_id} (image {img.name})"
        check_intrinsics(os.path.join(model_dir, "cameras.bin"), where, fx, fy, cx, cy, camera.width, camera.height)
        sx, sy = width / camera.width, height / camera.height
        K = torch.tensor([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]], dtype=torch.float32)
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3, :] = torch.from_numpy(img.cam_from_world().matrix())
        views.append(
            View(
                name=img.name,
                image_path=os.path.join(image_dir, img.name),
                width=width,
                height=height,
                K=K,
                viewmat=viewmat.float(),
                resize_from=image_dir if resize_by > 1 else None,
            )
        )

    points3d = reconstruction.points3D
    if len(points3d):
        points = torch.from_numpy(np.array([p.xyz for p in points3d.values()], dtype=np.float32))
        colors = torch.from_numpy(np.array([p.color for p in points3d.values()], dtype=np.uint8))
    elif not random_init:
        raise InputError(
            model_dir,
            "the COLMAP model has no 3D points to start from; pass --random-init to start from random "
            "points inside the cameras' common view instead",
        )
    else:
        points, colors = random_points_in_frustums(views)
        note = (
            "the COLMAP model has no 3D points: random initial points inside the cameras' common view (--random-init)"
        )
        log.warning("%s: %s", model_dir, note)
        notes.append(note)
    return views, points, colors, notes
