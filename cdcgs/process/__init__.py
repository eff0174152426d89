"""From photos or a video to a scene that ``cdcgs train --data`` reads (``cdcgs process``):
structure from motion with pycolmap, undistortion, downscaled copies, a summary."""

from .pipeline import MAPPERS, MATCHERS, ProcessOptions, process

__all__ = ["MAPPERS", "MATCHERS", "ProcessOptions", "process"]
