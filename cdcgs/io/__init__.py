"""Scene input (COLMAP, transforms.json), model output (PLY) and checkpoints."""

from ..errors import InputError
from .checkpoint import load_checkpoint, save_checkpoint
from .ply import GaussianPly, read_ply, write_ply
from .scene import Scene, load_scene
from .views import View, load_images, scene_extent, split_views

__all__ = [
    "GaussianPly",
    "InputError",
    "Scene",
    "View",
    "load_checkpoint",
    "load_images",
    "load_scene",
    "read_ply",
    "save_checkpoint",
    "scene_extent",
    "split_views",
    "write_ply",
]
