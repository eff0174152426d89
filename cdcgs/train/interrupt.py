"""SIGINT (Ctrl-C) and SIGTERM (what schedulers send) during a training.

While the trainer is *deferring* (in its loop, and while it writes a checkpoint) the first signal
only sets a flag, which the loop reads after each whole iteration: the run then stops at an
iteration boundary and its checkpoint counts exactly the updates applied. Elsewhere (loading the
scene, the final evaluation), and for a second signal anywhere, the signal stops the run at once
with :class:`Interrupted` (``clean=False``): the trainer then writes nothing, and the files already
written stay whole because every write is atomic (temporary file, then rename).
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["Interrupted", "StopSignals"]

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A run stopped by a signal. ``clean``: at an iteration boundary (the state is whole and
    may be saved); otherwise in the middle of something (save nothing). ``exit_status`` is the
    shell's convention, 128 + the signal number."""

    def __init__(self, signum: int, clean: bool):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.clean = clean

    @property
    def exit_status(self) -> int:
        return 128 + self.signum


class StopSignals:
    """Catches SIGINT and SIGTERM from ``__enter__`` to ``__exit__`` (the previous handlers come
    back); only in the main thread, where Python delivers signals (elsewhere it does nothing)."""

    def __init__(self):
        self.pending: int | None = None  # the first signal received
        self._deferring = 0
        self._previous: dict = {}

    def __enter__(self) -> StopSignals:
        self.pending = None
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}

    def _handle(self, signum, frame) -> None:
        first = self.pending is None
        if first:
            self.pending = signum
        if first and self._deferring:
            return
        raise Interrupted(signum, clean=False)

    @contextlib.contextmanager
    def deferred(self):
        """A block that the first signal does not cut (nestable)."""
        self._deferring += 1
        try:
            yield
        finally:
            self._deferring -= 1

    def raise_pending(self) -> None:
        """Stop cleanly (``Interrupted(clean=True)``) if a signal came while deferring."""
        if self.pending is not None:
            raise Interrupted(self.pending, clean=True)
