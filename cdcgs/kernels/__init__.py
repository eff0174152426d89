"""Pure-Warp kernels of cdcgs: usable with ``wp.launch`` and Warp arrays alone, no torch needed."""

from .binning import TILE_SIZE, TileBins, bin_gaussians, count_tiles_kernel, emit_keys_kernel, gather_counts_kernel, tile_ranges_kernel
from .blend import blend_backward_kernel, blend_backward_lean_kernel, blend_forward_kernel
from .projection import (
    Camera,
    make_camera,
    project_gaussians_kernel,
    sh_to_color_backward_kernel,
    sh_to_color_grouped_backward_kernel,
    sh_to_color_kernel,
)

__all__ = [
    "TILE_SIZE",
    "Camera",
    "TileBins",
    "bin_gaussians",
    "blend_backward_kernel",
    "blend_backward_lean_kernel",
    "blend_forward_kernel",
    "count_tiles_kernel",
    "emit_keys_kernel",
    "gather_counts_kernel",
    "make_camera",
    "project_gaussians_kernel",
    "sh_to_color_backward_kernel",
    "sh_to_color_grouped_backward_kernel",
    "sh_to_color_kernel",
    "tile_ranges_kernel",
]
