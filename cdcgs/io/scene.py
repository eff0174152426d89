"""The scene record the trainer needs, read from a COLMAP folder or a transforms.json."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import torch

from ..errors import InputError, OptionError
from .colmap import read_colmap
from .transforms import read_transforms
from .views import View, load_images, read_view_names, scene_extent, split_views, unknown_view_names

__all__ = ["Scene", "load_scene"]


@dataclass
class Scene:
    """A scene ready to train on.

    Attributes:
        root: the folder it was read from. source: "colmap" or "transforms".
        train, test: views sorted by name. points [P, 3] float32 and colors [P, 3] uint8: the
        initial point cloud. extent: 1.1 x the largest distance of a training camera centre
        from their mean (3DGS), in world units.
    """

    root: str
    source: str
    train: list[View]
    test: list[View]
    points: torch.Tensor
    colors: torch.Tensor
    extent: float
    notes: list[str] = field(default_factory=list)

    @property
    def views(self) -> list[View]:
        return sorted(self.train + [v for v in self.test if v not in self.train], key=lambda v: v.name)


def load_scene(
    path,
    *,
    images: str | None = None,
    factor: int | None = None,
    test_every: int = 8,
    train_on_all: bool = False,
    test_views=None,
    device="cpu",
    load_images_now: bool = True,
    num_threads: int | None = None,
    skip_missing: bool = False,
    random_init: bool = False,
    progress: bool = True,
) -> Scene:
    """Load a COLMAP folder (``sparse/0`` or ``sparse``) or a NeRF-style ``transforms.json`` scene.

    Args:
        path: the scene folder (or a transforms .json file).
        images: COLMAP image folder name, e.g. "images_4"; its suffix gives the factor.
        factor: downsampling factor (1, 2, 4, 8): COLMAP folder ``images_{factor}``, or resize on
            load when that folder is missing; transforms.json images are resized by it.
        test_every: hold out every n-th view by sorted name (0: none). train_on_all: train on all.
        test_views: hold out these views instead: a file of image names, one per line (a run's
            test_views.txt), or a list of names; every one must be a view of the scene.
        device: where the uint8 images live. load_images_now: read the pictures now.
        skip_missing: skip frames whose image file is missing (reported) instead of refusing.
        random_init: a COLMAP model without 3-D points starts from random points (announced)
            instead of being refused.

    Raises:
        InputError: a missing or malformed folder, model, image or transforms file.
    """
    path = os.fspath(path)
    if factor is not None and (isinstance(factor, bool) or not isinstance(factor, int) or factor < 1):
        raise OptionError(f"factor must be a positive int, got {factor!r}")
    if not os.path.exists(path):
        raise InputError(path, "no such scene folder")
    transforms = path if path.endswith(".json") else os.path.join(path, "transforms.json")
    if os.path.isfile(transforms):
        if images is not None:
            raise OptionError("images= names a COLMAP image folder; for transforms.json scenes use factor=")
        views, points, colors, notes = read_transforms(transforms, factor=factor or 1, skip_missing=skip_missing)
        root, source = os.path.dirname(os.path.abspath(transforms)), "transforms"
    elif os.path.isdir(path):
        views, points, colors, notes = read_colmap(
            path, images=images, factor=factor, skip_missing=skip_missing, random_init=random_init
        )
        root, source = path, "colmap"
    else:
        raise InputError(path, "not a scene: expected a folder with sparse/0 (COLMAP) or a transforms.json")
    if not views:
        raise InputError(path, "the scene has no views")
    from_file = test_views is not None and not isinstance(test_views, (list, tuple, set, frozenset))
    test_names = read_view_names(test_views) if from_file else test_views
    if test_names is not None:
        missing = unknown_view_names(test_names, views)
        if missing:
            shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
            where = os.fspath(test_views) if from_file else path
            raise InputError(
                where, f"{len(missing)} of the {len(set(test_names))} test view names are not views of {path}: {shown}"
            )
    train, test = split_views(views, test_every, train_on_all, test_names)
    if not train:
        raise InputError(path, f"no training views: {len(views)} view(s) and every one is held out")
    scene = Scene(
        root=root,
        source=source,
        train=train,
        test=test,
        points=points,
        colors=colors,
        extent=scene_extent(train),
        notes=notes,
    )
    if load_images_now:
        load_images(scene.views, device=device, num_threads=num_threads, progress=progress)
    return scene
