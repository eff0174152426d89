"""Training steps that never wait for the device (``--sync-free``).

A render sizes its sort by the view's number of (tile, Gaussian) pairs, and reading that count
makes the host wait, once a view, for every kernel queued before it. With ``--sync-free`` a view
whose count is known from an earlier render is rendered into a fixed number of slots instead
(``rasterize(capacity=...)``: the count seen last, scaled by how much the Gaussians grew since, times
:data:`MARGIN`, plus :data:`FLOOR`), and the host runs ahead: it reads the device only where a
training reads it anyway (logs, densification, evaluation, checkpoints, the end; at least every
:data:`READ_EVERY` iterations).

What a render did not check is checked on the device (:data:`cdcgs.kernels._lookahead.note_render_kernel`):
a render whose pairs overflowed its slots, or whose inputs held NaN, sets a flag, ``halt``, and
records its iteration. While ``halt`` is set, every kernel that changes the training's state does
nothing: Adam (``FusedAdam``), the densification statistics, MCMC's noise and the guard's running
means. At the next read the trainer sees the flag, goes back to the iteration that set it (the host
keeps what it needs to start each iteration again: the view order, the spherical-harmonics degree,
Adam's step counts) and takes it again, now with the count that the device recorded. So no gradient
of an incomplete render is ever applied, and without an overflow the run is the one that reads
every count (``tests/test_lookahead.py``). A step's guard records and densification statistics
wait for its last render, so that a halt on a later view of a batch stops the earlier views' too.
Before the first step every view's count for the Gaussians the training starts from is taken from
one binning of each view and one wait for all (:meth:`Lookahead.prime`), so the first renders take
slots too. A view whose count at the render's scale is unknown (a new resolution of the schedule),
or whose slots would exceed ``MAX_CAPACITY``, reads its count as before. Callbacks (the viewer)
see each iteration as it is taken, those taken again included.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from .._interop import launch, warp_scope, wp_arg
from ..kernels._lookahead import note_render_kernel
from ..render import MAX_CAPACITY

__all__ = ["FLOOR", "MARGIN", "READ_EVERY", "Halted", "Lookahead", "halt_refusal"]


def halt_refusal(config, strategy) -> tuple[str, str] | None:
    """Why a training cannot render without reading its counts (``--sync-free``, and the steps
    replayed as CUDA graphs, which build on it), and what to change: (why, what to change), or
    None. A halt must stop every update until the host has read it (on several processes, every
    process's: the halt travels with the step's all-reduce)."""
    if config.optimizer not in ("adam", "selective"):
        return f"halts Adam on the device, which --optimizer {config.optimizer} cannot", "use adam or selective"
    if getattr(strategy, "complexity_schedule", None) == "online" and strategy.needs_complexity:
        return (
            "cannot be combined with --complexity-schedule online, which adds every render to Γ with torch "
            "operations that a halt does not stop",
            "use the full schedule",
        )
    return None


# Slots of a view = its last count x (Gaussians now / Gaussians then) x MARGIN + FLOOR. The sort's
# work grows with the slots; an overflow costs the iterations since the last read.
MARGIN = 1.25
FLOOR = 4096

# The most iterations between two reads (a larger --log-every would let the host run further
# ahead, keep more iterations' host state, and lose more to an overflow).
READ_EVERY = 100

# Causes of a halt, as note_render_kernel writes them.
OVERFLOW = 1


class Halted:
    """What a read found: the first iteration whose render overflowed (``cause`` 1) or met a
    non-finite input (``cause`` 2 + the input's index), and that render's count of pairs."""

    def __init__(self, step: int, cause: int, count: int):
        self.step, self.cause, self.count = step, cause, count

    @property
    def overflowed(self) -> bool:
        return self.cause == OVERFLOW


class Lookahead:
    """The device flags and the counts of one training's views (``num_views`` training views)."""

    def __init__(self, device: torch.device, num_views: int):
        self.device = torch.device(device)
        self.halt = torch.zeros(1, dtype=torch.int32, device=self.device)
        self._first = torch.zeros(3, dtype=torch.int32, device=self.device)
        self._counts = torch.zeros(max(num_views, 1), dtype=torch.int32, device=self.device)
        # view -> (count, Gaussians then, scale, iteration of that render)
        self._known: dict[int, tuple[int, int, int, int]] = {}
        # On several processes: the counts every process knows (the union of theirs at the last
        # read), which alone may decide what every process must do alike (a replayed step).
        self._agreed: dict[int, tuple[int, int, int, int]] = {}
        self._noted: dict[int, tuple[int, int, int]] = {}  # views rendered with slots since the last read
        self.renders = {"counted": 0, "within": 0}
        self.primed = 0  # views whose counts a binning before the training gave (Trainer._prime_counts)
        self.rewinds = 0
        self.redone = 0  # iterations taken again
        # the Γ passes' views (CDC-GS): binned into slots, reading their count, read again after an overflow
        self.gamma_views = {"within": 0, "counted": 0, "counted_again": 0}

    def capacity(self, view: int, gaussians: int, scale: int = 1, agreed: bool = False) -> int | None:
        """Slots for ``view`` rendered at 1/``scale`` with ``gaussians`` Gaussians, or None: read
        the count (never rendered at this scale, or more slots than a render takes). ``agreed``:
        from the counts every process knows alike (:meth:`merge`), not this process's own."""
        known = (self._agreed if agreed else self._known).get(view)
        if known is None or known[2] != scale:
            return None
        count, then, _, _ = known
        slots = math.ceil(count * max(1.0, gaussians / max(then, 1)) * MARGIN) + FLOOR
        return slots if slots <= MAX_CAPACITY else None

    def prime(self, counts: list[int], gaussians: int, scale: int = 1, iteration: int = 0) -> None:
        """Every view's count (``counts[view]``) of a binning of ``gaussians`` Gaussians at 1/``scale``
        before ``iteration``, no render's: its first renders take slots instead of reading theirs."""
        for view, count in enumerate(counts):
            self._known[view] = (count, gaussians, scale, iteration)
        self.primed += len(counts)

    def counted(self, view: int, count: int, gaussians: int, scale: int = 1, iteration: int = 0) -> None:
        """A render of ``view`` at ``iteration`` that read its ``count``."""
        self._known[view] = (count, gaussians, scale, iteration)
        self.renders["counted"] += 1

    def note(
        self, info, step: int, view: int, gaussians: int, scale: int = 1, where: torch.Tensor | None = None
    ) -> None:
        """After a render with a capacity (``info`` its RasterizeInfo) of ``view`` at iteration
        ``step``: its count and flags, kept on the device (one launch). ``where``: an int32 device
        tensor that holds (iteration, view) when the launch runs (a captured step's); the host's
        ``step`` and ``view`` then only say what was rendered (:meth:`replayed`)."""
        if where is None:
            self.replayed(view, gaussians, scale, step)
        no_where = torch.empty(0, dtype=torch.int32, device=self.device) if where is None else where
        with warp_scope(self.device):
            launch(
                note_render_kernel,
                1,
                inputs=[wp_arg(info.pending, wp.int32), int(step), int(view), wp_arg(no_where, wp.int32)],
                outputs=[wp_arg(self.halt, wp.int32), wp_arg(self._first, wp.int32), wp_arg(self._counts, wp.int32)],
            )

    def replayed(self, view: int, gaussians: int, scale: int = 1, iteration: int = 0) -> None:
        """A render of ``view`` at ``iteration`` with a capacity whose note runs on the device (a
        replayed step)."""
        self._noted[view] = (gaussians, scale, iteration)
        self.renders["within"] += 1

    def read(self, always: bool = False) -> Halted | None:
        """One host synchronisation: the counts of the views rendered since the last read, and the
        halt (cleared here), or None when no render halted. ``always``: read the flags even when
        no render of this process had slots since the last read (on several processes another
        process's halt reaches this one's flags through the all-reduce)."""
        if not self._noted and not always:  # only a render with slots sets the halt, and the last read cleared it
            return None
        values = torch.cat([self.halt, self._first, self._counts]).tolist()
        halted, counts = values[:4], values[4:]
        for view, (gaussians, scale, iteration) in self._noted.items():
            self._known[view] = (counts[view], gaussians, scale, iteration)
        self._noted.clear()
        if not halted[0]:
            return None
        self.halt.zero_()
        self._first.zero_()
        return Halted(*halted[1:])

    def known(self) -> dict[int, tuple[int, int, int, int]]:
        """This process's counts: view -> (count, Gaussians then, scale, iteration)."""
        return dict(self._known)

    def merge(self, tables: list[dict]) -> None:
        """Take the counts of every process (``tables``: :meth:`known` of each, in rank order),
        the latest render of each view winning; every process then holds the same counts, the
        agreed ones included."""
        merged: dict[int, tuple[int, int, int, int]] = {}
        for table in tables:
            for view, entry in table.items():
                if view not in merged or entry[3] > merged[view][3]:
                    merged[view] = entry
        self._known = merged
        self._agreed = dict(merged)

    def forget(self) -> None:
        """Every view reads its count again (after a change that moves the counts, e.g. a new
        render size)."""
        self._known.clear()
        self._agreed.clear()

    def summary(self) -> dict:
        """metrics.json's account: renders that read their count and that did not, halts, the
        iterations taken again and, where Γ passes ran, how their views were binned."""
        summary = {
            "views_primed": self.primed,
            "renders_counted": self.renders["counted"],
            "renders_within_capacity": self.renders["within"],
            "rewinds": self.rewinds,
            "iterations_redone": self.redone,
        }
        if any(self.gamma_views.values()):
            summary.update({f"gamma_views_{how}": count for how, count in self.gamma_views.items()})
        return summary
