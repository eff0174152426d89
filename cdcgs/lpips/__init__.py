"""LPIPS (v0.1, VGG and AlexNet) for evaluation, without torchvision, with weights that work
offline (``cdcgs weights lpips``) and are checked on every load."""

from .network import LPIPS
from .weights import WeightsUnavailable, cache_dir, install, load_lpips, weights_path

__all__ = ["LPIPS", "WeightsUnavailable", "cache_dir", "install", "load_lpips", "weights_path"]
