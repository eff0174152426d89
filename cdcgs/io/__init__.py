"""Scene input (COLMAP, transforms.json), model output (PLY) and checkpoints."""

from ..errors import InputError
from .checkpoint import capture_rng_state, load_checkpoint, restore_rng_state, save_checkpoint
from .ply import GaussianPly, read_ply, write_ply
from .scene import Scene, View, load_scene, scene_extent, split_views

__all__ = [
    "GaussianPly",
    "InputError",
    "Scene",
    "View",
    "capture_rng_state",
    "load_checkpoint",
    "load_scene",
    "read_ply",
    "restore_rng_state",
    "save_checkpoint",
    "scene_extent",
    "split_views",
    "write_ply",
]
