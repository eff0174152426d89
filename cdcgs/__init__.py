"""cdcgs: 3D Gaussian Splatting with CDC-GS densification, on NVIDIA Warp kernels (CPU and CUDA).

``cdcgs.rasterize`` is the torch face (``cdcgs.prepare_camera`` checks and builds a camera once for
repeated renders); ``cdcgs.kernels`` holds the pure-Warp kernels, which import no torch, so that
they can be launched from any Warp program. Importing cdcgs initialises nothing: Warp's runtime
starts on the first render.
"""

__all__ = [
    "PendingBins",
    "PreparedCamera",
    "RasterizeInfo",
    "bin_view",
    "prepare_camera",
    "rasterize",
    "start_bin_view",
]
__version__ = "0.1.0"


def __getattr__(name):
    # Imported lazily so that `import cdcgs.kernels` does not pull in torch.
    if name in __all__:
        from . import render

        return getattr(render, name)
    raise AttributeError(f"module 'cdcgs' has no attribute {name!r}")
