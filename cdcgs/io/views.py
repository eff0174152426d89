"""One camera view and what every scene reader shares: splits, extent, image reading, missing-file
reports, random initial points.

Conventions, converted once at load: world-to-camera 4x4 matrices, camera x right, y down,
z forward (COLMAP); intrinsics in pixels of the loaded images, with continuous coordinates
(pixel (i, j) centred at (i + 0.5, j + 0.5)).
"""

from __future__ import annotations

import logging
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image

from ..errors import InputError, OptionError
from ._pycolmap import import_pycolmap

log = logging.getLogger("cdcgs")

__all__ = [
    "View",
    "check_intrinsics",
    "load_images",
    "random_points_in_frustums",
    "read_view_names",
    "report_missing",
    "scene_extent",
    "split_views",
    "unknown_view_names",
]


@dataclass
class View:
    """One training or test image with its pinhole camera.

    K [3, 3] and viewmat [4, 4] are float32 CPU tensors (world-to-camera); image is the
    [H, W, 3] uint8 picture on the scene's device once loaded.
    """

    name: str
    image_path: str
    width: int
    height: int
    K: torch.Tensor
    viewmat: torch.Tensor
    image: torch.Tensor | None = None
    # Set when the file is not already at (width, height): it is resized on load (a missing
    # factor folder) and, with undistort_camera (a pycolmap camera), undistorted first.
    resize_from: str | None = None
    undistort_camera: object | None = None

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3].double(), self.viewmat[:3, 3].double()
        return (-R.T @ t).float()


def report_missing(path: str, message: str, skip_missing: bool, notes: list[str]) -> None:
    """Refuse a scene with missing image files, or (``skip_missing``) warn and note it."""
    if not skip_missing:
        raise InputError(path, message + " (skip_missing skips them)")
    log.warning("%s: %s; skipping them", path, message)
    notes.append(f"{path}: {message}; skipped")


def check_intrinsics(
    source: str, where: str, fx: float, fy: float, cx: float, cy: float, width: int, height: int
) -> None:
    """Refuse intrinsics that cannot be a real pinhole camera of a ``width`` x ``height`` image:
    non-finite or non-positive focal lengths, a field of view outside 0.01°..179° (focal length
    over 0.0087 to 11,000 times the image size), or a principal point far outside the image.

    Raises:
        InputError: naming ``source`` (the file) and ``where`` (the camera or frame).
    """
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    for name, value in values.items():
        if not math.isfinite(value):
            raise InputError(source, f"{where}: {name} is {value}, not a finite number")
    for name, focal, size in (("fx", fx, width), ("fy", fy, height)):
        if not 0.0087 * size <= focal <= 11_000 * size:
            raise InputError(
                source,
                f"{where}: focal length {name} = {focal:g} px is not plausible for an image {size} px across "
                f"(expected {0.0087 * size:g} to {11_000 * size:g}: a field of view of 0.01 to 179 degrees)",
            )
    for name, centre, size in (("cx", cx, width), ("cy", cy, height)):
        if not -size <= centre <= 2 * size:
            raise InputError(
                source, f"{where}: principal point {name} = {centre:g} px lies far outside the {size} px image"
            )


def split_views(
    views: list[View], test_every: int = 8, train_on_all: bool = False, test_names=None
) -> tuple[list[View], list[View]]:
    """Sort by image name; every ``test_every``-th (index % test_every == 0) is held out for testing.

    With ``train_on_all`` the training set holds every view (the test views are still listed, for
    reporting on them). ``test_every`` 0 holds out nothing. ``test_names`` (image names) holds out
    exactly those views instead of every n-th: the way to test two models of the same photos on the
    same photos when one of them lacks a view (every n-th by name would shift past the gap).

    Raises:
        OptionError: a bad ``test_every``, or a name in ``test_names`` that is not a view of the scene.
    """
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 0:
        raise OptionError(f"test_every must be a non-negative int, got {test_every!r}")
    views = sorted(views, key=lambda v: v.name)
    if test_names is None:
        held = [bool(test_every) and i % test_every == 0 for i in range(len(views))]
    else:
        if isinstance(test_names, str):
            raise OptionError("test_names must be a list of image names, not one string")
        missing = unknown_view_names(test_names, views)
        if missing:
            raise OptionError(f"test_names: {len(missing)} name(s) are not views: {', '.join(missing[:8])}")
        wanted = set(test_names)
        held = [v.name in wanted for v in views]
    test = [v for v, h in zip(views, held) if h]
    train = views if train_on_all else [v for v, h in zip(views, held) if not h]
    return train, test


def unknown_view_names(names, views: list[View]) -> list[str]:
    """The names, sorted, that are no view's image name."""
    return sorted(set(names) - {v.name for v in views})


def read_view_names(path) -> list[str]:
    """Image names, one per line, from a text file: a run's ``test_views.txt`` or a list written by
    hand. Blank lines and lines that start with ``#`` are skipped; a name keeps its inner spaces.
    An empty list (no name) is refused: ``--test-every 0`` holds out nothing.

    Raises:
        InputError: the file is missing, unreadable, not text, or names no image.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8-sig") as f:  # -sig: a byte-order mark is not part of the first name
            lines = f.read().splitlines()
    except FileNotFoundError:
        raise InputError(path, "no such file of view names") from None
    except IsADirectoryError:
        raise InputError(path, "a folder, not a file of view names (one image name per line)") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"unreadable as a text file of view names ({e})") from None
    names = [n for n in (line.strip() for line in lines) if n and not n.startswith("#")]
    if not names:
        raise InputError(path, "names no view (expected one image name per line)")
    return list(dict.fromkeys(names))


def scene_extent(views: list[View]) -> float:
    """1.1 x the largest distance of a camera centre from the mean centre (3DGS's scene radius)."""
    centers = torch.stack([v.center.double() for v in views])
    radius = (centers - centers.mean(0)).norm(dim=-1).max().item()
    return 1.1 * max(radius, 1e-6)


def _read_image(view: View) -> np.ndarray:
    path = view.image_path
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            if view.undistort_camera is not None:
                pycolmap = import_pycolmap()

                bitmap = pycolmap.Bitmap.from_array(np.asarray(im, dtype=np.uint8))
                undistorted, _ = pycolmap.undistort_image(
                    pycolmap.UndistortCameraOptions(), bitmap, view.undistort_camera
                )
                im = Image.fromarray(undistorted.to_array())
            if view.resize_from is not None or im.size != (view.width, view.height):
                if view.resize_from is None:
                    raise InputError(
                        path, f"image is {im.size[0]}x{im.size[1]} but its camera says {view.width}x{view.height}"
                    )
                im = im.resize((view.width, view.height), Image.LANCZOS)
            return np.array(im, dtype=np.uint8)
    except InputError:
        raise
    except (OSError, ValueError) as err:
        raise InputError(path, f"cannot read the image: {err}") from None


def random_points_in_frustums(
    views: list[View], count: int = 100_000, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random initial points [count, 3] float32 (and random uint8 colours) that every camera sees.

    Candidates are drawn uniformly in the box around the camera centres and the points one scene
    radius in front of each camera; those inside every view frustum are kept (when too few are,
    those seen by the most cameras).
    """
    g = torch.Generator().manual_seed(seed)
    centers = torch.stack([v.center for v in views]).double()
    radius = scene_extent(views) / 1.1
    forward = torch.stack([v.viewmat[2, :3] for v in views]).double()
    anchors = torch.cat([centers, centers + radius * forward])
    lo, hi = anchors.min(0).values, anchors.max(0).values
    lo, hi = lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo)
    kept, seen_counts = [], []
    total = 0
    for _ in range(20):
        candidates = lo + (hi - lo) * torch.rand(4 * count, 3, generator=g, dtype=torch.float64)
        seen = torch.zeros(len(candidates), dtype=torch.int32)
        for v in views:
            cam = candidates @ v.viewmat[:3, :3].double().T + v.viewmat[:3, 3].double()
            z = cam[:, 2]
            u = v.K[0, 0] * cam[:, 0] / z.clamp_min(1e-9) + v.K[0, 2]
            w = v.K[1, 1] * cam[:, 1] / z.clamp_min(1e-9) + v.K[1, 2]
            seen += ((z > 1e-3) & (u >= 0) & (u < v.width) & (w >= 0) & (w < v.height)).int()
        kept.append(candidates)
        seen_counts.append(seen)
        total += int((seen == len(views)).sum())
        if total >= count:
            break
    candidates, seen = torch.cat(kept), torch.cat(seen_counts)
    order = torch.argsort(seen, descending=True, stable=True)[:count]
    points = candidates[order].float()
    colors = torch.randint(0, 256, (len(points), 3), generator=g, dtype=torch.uint8)
    return points, colors


def load_images(views: list[View], device="cpu", num_threads: int | None = None, progress: bool = True) -> None:
    """Read every view's picture into ``view.image`` ([H, W, 3] uint8 on ``device``), in threads."""
    from tqdm import tqdm

    num_threads = num_threads or min(16, (os.cpu_count() or 2) * 2)
    with ThreadPoolExecutor(max_workers=num_threads) as pool:
        arrays = pool.map(_read_image, views)
        for view, array in tqdm(
            zip(views, arrays), total=len(views), desc="loading images", unit="img", disable=not progress
        ):
            view.image = torch.from_numpy(array).to(device)
