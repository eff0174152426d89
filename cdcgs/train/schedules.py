"""Schedules: the position learning rate, the training resolution and the primitive budget
(DashGaussian).

The resolution schedule follows DashGaussian (Chen et al., CVPR 2025): train at a reduced
resolution early and raise it as the optimisation moves from the low to the high frequencies of
the photos. From the photos' centred Fourier magnitude spectra:

- each photo's largest useful downscale s is the one whose central window of 1/s of the spectrum
  (in each axis) holds 1/``start_factor`` of its energy; the schedule starts at the smallest of
  them (at most ``max_scale``);
- the energy of that window of the photos' mean spectrum, E_min, rises to the whole energy E in
  ``levels - 1`` equal steps; level i's scale is the window that holds its energy, and it begins
  at ``until * log(E_(i-1) / E_min) / log(E / E_min)`` (the log spaces the levels so that the
  low resolutions take fewer iterations); between two levels the pixel count 1/s^2 grows
  linearly; from ``until`` (the end of densification) on, full resolution;
- the trainer renders at ``size // int(s)``; the position learning rate starts decaying only when
  the scale drops below 2 (:func:`position_lr`'s ``decay_from``).

The primitive budget (``--budget-schedule dash``, :func:`dash_budget`) is DashGaussian's other
half: the count may grow at a densification step to the initial count plus the room to the upper
bound divided by s^(2 - step / until), s the step's downscale (so the room opens with the pixel
count early and with the scale late), never by more than ``DASH_GROWTH_RATE`` of the count in one
step, and to the whole bound from the last densification step before ``until``. Without a preset
bound the bound is the initial count plus a momentum (:func:`dash_momentum`) that starts at
``DASH_MOMENTUM_START`` times the initial count and follows the number of Gaussians that each
densification step selects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .config import LearningRates

__all__ = [
    "DASH_GROWTH_RATE",
    "DASH_MOMENTUM_DECAY",
    "DASH_MOMENTUM_START",
    "DASH_MOMENTUM_STEP_CAP",
    "ResolutionSchedule",
    "dash_budget",
    "dash_momentum",
    "dash_schedule",
    "position_lr",
    "solve_window",
    "window_energy",
]

# DashGaussian's constants of the primitive budget (its TrainingScheduler).
DASH_GROWTH_RATE = 0.2  # the count grows by at most this share in one densification step
DASH_MOMENTUM_START = 5  # the momentum starts at this many times the initial count
DASH_MOMENTUM_DECAY = 0.98  # the share of the momentum that a densification step keeps
DASH_MOMENTUM_STEP_CAP = 1_000_000  # at most this many selected Gaussians count in one step


def position_lr(step: int, total_steps: int, lrs: LearningRates, extent: float, decay_from: int = 0) -> float:
    """Exponential decay from means_init to means_final (x extent) over the run (3DGS); with
    ``decay_from`` > 0 the rate stays at means_init until that step and decays over the rest
    (DashGaussian's delayed decay)."""
    t = (step - decay_from) / max(total_steps - decay_from, 1)
    t = min(max(t, 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(lrs.means_init) + t * math.log(lrs.means_final))


def _summed_area(spectrum: torch.Tensor) -> torch.Tensor:
    """[H + 1, W + 1] float64 prefix sums of an [H, W] map (0 in the first row and column)."""
    table = torch.zeros(spectrum.shape[0] + 1, spectrum.shape[1] + 1, dtype=torch.float64)
    table[1:, 1:] = spectrum.double().cpu().cumsum(0).cumsum(1)
    return table


def window_energy(table: torch.Tensor, fraction: float) -> float:
    """Energy of the central window of a centred spectrum (its summed-area ``table``) that spans
    ``fraction`` of each axis: rows c - half .. c + half - 1 with c = (H + 1) // 2 and half =
    int(H * fraction) // 2, the same for columns."""
    h, w = table.shape[0] - 1, table.shape[1] - 1
    ch, cw = (h + 1) // 2, (w + 1) // 2
    hh, hw = int(h * fraction) // 2, int(w * fraction) // 2
    r0, r1, c0, c1 = ch - hh, ch + hh, cw - hw, cw + hw
    return float(table[r1, c1] - table[r0, c1] - table[r1, c0] + table[r0, c0])


def solve_window(table: torch.Tensor, energy: float) -> float:
    """The scale s (>= 1) whose window (1/s of each axis) is the smallest holding ``energy``:
    bisection on 1/s over (0, 1], 64 halvings."""
    low, high = 0.0, 1.0
    for _ in range(64):
        mid = (low + high) / 2
        if window_energy(table, mid) < energy:
            low = mid
        else:
            high = mid
    return 1.0 / ((low + high) / 2)


@dataclass(frozen=True)
class ResolutionSchedule:
    """Downscale per step: ``scales[i]`` (level i, ``scales[0]`` the largest, the last 1) holds at
    ``begins[i + 1]``; ``begins`` has one entry more than ``scales``, the last being ``until``."""

    scales: tuple[float, ...]
    begins: tuple[int, ...]
    until: int

    def scale_at(self, step: int) -> int:
        """The integer downscale at ``step``: the scale interpolated linearly in 1/s^2 between the
        two levels around the step, truncated; 1 from ``until`` on."""
        if step >= self.until:
            return 1
        i = 1
        while i + 1 < len(self.begins) and step >= self.begins[i + 1]:
            i += 1
        start, end = self.begins[i], self.begins[i + 1]
        before, after = self.scales[i - 1], self.scales[i]
        share = (step - start) / max(end - start, 1)
        pixels = share * (1 / after**2 - 1 / before**2) + 1 / before**2
        return max(int((1 / pixels) ** 0.5), 1)

    def decay_from(self) -> int:
        """The step where the scale first drops below 2 (where the position rate starts decaying)."""
        for begin, scale in zip(self.begins, self.scales):
            if scale < 2:
                return begin
        return self.until


def dash_schedule(
    images: list[torch.Tensor],
    until: int,
    *,
    levels: int = 32,
    start_factor: float = 4.0,
    max_scale: float = 8.0,
    min_size: int = 16,
) -> ResolutionSchedule:
    """DashGaussian's schedule from the training photos ([H, W, 3] uint8 or float tensors; the mean
    spectrum uses the photos of the first photo's size). See the module's docstring. The start
    scale also keeps every render at least ``min_size`` pixels on its short side (SSIM's window
    is 11 pixels wide; DashGaussian's photos are never small enough to need this)."""
    if not images:
        raise ValueError("the resolution schedule needs at least one training photo")
    if levels < 2 or start_factor <= 1 or max_scale < 1 or until < 1:
        raise ValueError(
            f"dash_schedule needs levels >= 2, start_factor > 1, max_scale >= 1 and until >= 1, got {levels}, {start_factor}, {max_scale}, {until}"
        )
    shape = images[0].shape
    max_scale = max(min(max_scale, min(min(image.shape[:2]) for image in images) / min_size), 1.0)
    mean_spectrum = None
    count = 0
    for image in images:
        x = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
        magnitude = torch.fft.fftshift(torch.fft.fft2(x.permute(2, 0, 1)), dim=(-2, -1)).abs().sum(0)
        table = _summed_area(magnitude)
        max_scale = min(max_scale, solve_window(table, float(table[-1, -1]) / start_factor))
        if image.shape == shape:
            mean_spectrum = magnitude if mean_spectrum is None else mean_spectrum + magnitude
            count += 1
    table = _summed_area(mean_spectrum / count)
    total = float(table[-1, -1])
    lowest = window_energy(table, 1.0 / max_scale)
    span = math.log(total / lowest) if total > lowest else 1.0
    scales = [max_scale]
    begins = [0]
    energy_before = lowest
    for i in range(1, levels - 1):
        energy = lowest + (total - lowest) * i / (levels - 1)
        scales.append(solve_window(table, energy))
        begins.append(int(until * math.log(energy_before / lowest) / span))
        energy_before = energy
    scales.append(1.0)
    begins.append(int(until * math.log(energy_before / lowest) / span))
    begins.append(until)
    return ResolutionSchedule(tuple(scales), tuple(begins), until)


def dash_budget(step: int, scale: int, count: int, initial: int, bound: int, until: int, every: int) -> int:
    """The most Gaussians the densification step at ``step`` may grow to (DashGaussian's primitive
    scheduler): ``initial + int((bound - initial) / scale ** (2 - step / until))`` while a further
    densification step comes before ``until`` (``step + every < until``), ``bound`` from then on;
    never below ``count`` (no growth, but no removal either) nor above ``count`` grown by
    ``DASH_GROWTH_RATE``. ``scale`` is the downscale the step renders at, ``count`` the Gaussians
    before the step, ``initial`` those the run started with, ``bound`` the upper bound."""
    if step + every < until:
        wanted = initial + int((bound - initial) / scale ** (2 - step / until))
    else:
        wanted = bound
    return min(max(wanted, count), int(count * (1 + DASH_GROWTH_RATE)))


def dash_momentum(momentum: int, selected: int) -> int:
    """DashGaussian's estimate of the room above the initial count after a densification step that
    selected ``selected`` Gaussians: the larger of ``momentum`` and ``DASH_MOMENTUM_DECAY`` of it
    plus the selection (at most ``DASH_MOMENTUM_STEP_CAP``), truncated; it never falls."""
    return max(momentum, int(DASH_MOMENTUM_DECAY * momentum + min(DASH_MOMENTUM_STEP_CAP, selected)))
