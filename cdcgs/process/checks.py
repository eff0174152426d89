"""Checks of a processed model that need no reference: jumps in the camera path.

Photos taken one after another and video frames are named in the order they were taken, so each
camera's centre lies near the next one's. An incremental mapper that joins two parts of a capture
wrongly leaves a model in pieces whose reprojection error is still small; the seam shows as a
step between consecutive cameras many times longer than the path's usual step (bonsai's two
incremental models: 17x and 25x their median step at the seams, at most 1.8x elsewhere and in
the published model; docs/process.md).
"""

from __future__ import annotations

import re

import numpy as np

__all__ = ["JUMP_FACTOR", "ORDERED_RATIO", "natural_key", "path_jumps"]

# A step this many times the median step between consecutive cameras is a jump.
JUMP_FACTOR = 4.0
# The names follow the path when the median step is at most this many times the median distance
# from a camera to its nearest neighbour (about 1.1 for bonsai's photos; far larger when
# consecutive names are unrelated views of a collection).
ORDERED_RATIO = 2.5
MIN_VIEWS = 8


def natural_key(name: str) -> list:
    """Sort key that orders the numbers inside names by value (IMG_9 before IMG_10)."""
    return [int(part) if part.isdecimal() else part.lower() for part in re.split(r"(\d+)", name)]


def path_jumps(names: list[str], centres: np.ndarray, factor: float = JUMP_FACTOR) -> dict:
    """The camera path's jumps: cameras in the natural order of their names, and every step
    between consecutive ones longer than ``factor`` times the median step.

    Returns ``{"checked": bool, "reason": str (when not checked), "step_over_nearest": float,
    "jumps": [{"from", "to", "ratio"}]}``: the check runs when there are at least MIN_VIEWS
    cameras and the median step is at most ORDERED_RATIO times the median nearest-neighbour
    distance (the names follow the capture); ``ratio`` is the step over the median step.
    """
    centres = np.asarray(centres, dtype=np.float64)
    if centres.shape != (len(names), 3):
        raise ValueError(f"path_jumps needs one [3] centre per name, got {centres.shape} for {len(names)} names")
    result = {"checked": False, "jumps": []}
    if len(names) < MIN_VIEWS:
        return {**result, "reason": f"fewer than {MIN_VIEWS} registered views"}
    order = sorted(range(len(names)), key=lambda i: natural_key(names[i]))
    path = centres[order]
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    nearest = _nearest_distances(path)
    median_step, median_nearest = float(np.median(steps)), float(np.median(nearest))
    if median_step <= 0.0 or median_nearest <= 0.0:
        return {**result, "reason": "cameras share positions"}
    ratio = median_step / median_nearest
    result["step_over_nearest"] = round(ratio, 3)
    if ratio > ORDERED_RATIO:
        return {**result, "reason": "the names do not follow the camera path"}
    result["checked"] = True
    for i in np.flatnonzero(steps > factor * median_step):
        result["jumps"].append(
            {"from": names[order[i]], "to": names[order[i + 1]], "ratio": round(float(steps[i] / median_step), 1)}
        )
    return result


def _nearest_distances(points: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Each point's distance to its nearest other point (brute force, rows in chunks)."""
    nearest = np.empty(len(points))
    for start in range(0, len(points), chunk):
        block = np.linalg.norm(points[start : start + chunk, None] - points[None], axis=2)
        block[np.arange(len(block)), np.arange(start, start + len(block))] = np.inf
        nearest[start : start + chunk] = block.min(axis=1)
    return nearest
