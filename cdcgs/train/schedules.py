"""Learning-rate schedules."""

from __future__ import annotations

import math

from .config import LearningRates

__all__ = ["position_lr"]


def position_lr(step: int, total_steps: int, lrs: LearningRates, extent: float) -> float:
    """Exponential decay from means_init to means_final (x extent) over the run (3DGS)."""
    t = min(max(step / max(total_steps, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(lrs.means_init) + t * math.log(lrs.means_final))
