"""Scenes cdcgs can make or fetch: the procedural default scene, MipNeRF-360 downloads."""

from . import download, procedural

__all__ = ["download", "procedural"]
