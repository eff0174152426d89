"""Pure-Warp kernels of cdcgs: usable with ``wp.launch`` and Warp arrays alone, no torch needed.

What a ``wp.launch`` user needs: the camera (``make_camera``), the projection and SH colour kernels
and their adjoints, ``bin_gaussians`` (the tiles' depth-sorted lists), the blend kernels (launch
with ``dim=tiles_x * tiles_y * BLOCK_SIZE``, ``block_dim=BLOCK_SIZE``), the CDC-GS complexity pass (one
view a launch, or several: ``complexity_views_kernel``),
the exact KNN (``knn_search``), the training loss, L1 + D-SSIM, fused (``ssim_l1_*``: two
separable passes forward, two backward), and Adam on every row or on selected ones
(``fused_adam_kernel``: every parameter in one launch, ``adam_quads`` threads a parameter;
``selective_adam_kernel``: one parameter; ``AdamStep``: an Adam step that the SH adjoints apply
in place of writing the coefficients' gradients, or, empty, ``AdamStep()``), and 3DGS-MCMC's noise on the means
(``mcmc_noise_kernel``).
``examples/warp_launch.py`` renders an image with them.

The binning kernels that ``bin_gaussians`` runs stay importable from ``cdcgs.kernels.binning`` for
callers that manage their own buffers; the submodules (``projection``, ``binning``, ``blend``,
``knn``) stay importable as such.
"""

from ._constants import BLOCK_SIZE, TILE_SIZE
from .adam import AdamStep, adam_quads, fused_adam_kernel, selective_adam_kernel
from .binning import TileBins, bin_gaussians
from .blend import (
    blend_backward_kernel,
    blend_backward_lean_kernel,
    blend_forward_kernel,
    complexity_kernel,
    complexity_views_kernel,
)
from .knn import knn_search
from .loss import (
    ssim_l1_backward_kernel,
    ssim_l1_backward_rows_kernel,
    ssim_l1_forward_kernel,
    ssim_l1_forward_rows_kernel,
    ssim_l1_launch_size,
)
from .mcmc import mcmc_noise_kernel
from .projection import (
    SH_BLOCK,
    Camera,
    make_camera,
    project_gaussians_kernel,
    sh_to_color_backward_kernel,
    sh_to_color_grouped_backward_kernel,
    sh_to_color_kernel,
    sh_to_color_staged_backward_kernel,
)

__all__ = [
    "BLOCK_SIZE",
    "SH_BLOCK",
    "TILE_SIZE",
    "AdamStep",
    "Camera",
    "TileBins",
    "adam_quads",
    "bin_gaussians",
    "blend_backward_kernel",
    "blend_backward_lean_kernel",
    "blend_forward_kernel",
    "complexity_kernel",
    "complexity_views_kernel",
    "fused_adam_kernel",
    "knn_search",
    "make_camera",
    "mcmc_noise_kernel",
    "project_gaussians_kernel",
    "selective_adam_kernel",
    "sh_to_color_backward_kernel",
    "sh_to_color_grouped_backward_kernel",
    "sh_to_color_kernel",
    "sh_to_color_staged_backward_kernel",
    "ssim_l1_backward_kernel",
    "ssim_l1_backward_rows_kernel",
    "ssim_l1_forward_kernel",
    "ssim_l1_forward_rows_kernel",
    "ssim_l1_launch_size",
]
