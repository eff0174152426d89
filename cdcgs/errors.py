"""The exceptions cdcgs raises for bad user input: a file or folder (:class:`InputError`), an
option (:class:`OptionError`). The command line reports both in one line and exits with 2; every
other exception is a defect and keeps its traceback. :class:`NonFiniteError` is the render's
refusal of NaN or infinite inputs (a ValueError, as before), which the trainer turns into a report
of where the run's numbers went wrong. :class:`CapacityError` says that a render binned into a
fixed number of slots (``rasterize(capacity=...)``) needed more. :class:`PeerError` is what the
other processes of a sharded render raise when one process's arguments were wrong."""

import os

__all__ = ["CapacityError", "InputError", "NonFiniteError", "OptionError", "PeerError"]


class InputError(ValueError):
    """A file or folder given to cdcgs is missing, unreadable or malformed.

    Attributes:
        path: the file or folder at fault. problem: what is wrong with it.
    """

    def __init__(self, path, problem: str):
        self.path = os.fspath(path) if path is not None else None
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class OptionError(ValueError):
    """An option (a command-line flag or a configuration value) has a value cdcgs refuses."""


class NonFiniteError(ValueError):
    """A tensor handed to the render holds NaN or infinite values. ``name``: which argument."""

    def __init__(self, name: str):
        self.name = name
        super().__init__(f"{name} has non-finite values (NaN or inf)")


class PeerError(ValueError):
    """Another process of a sharded render (:func:`cdcgs.train.shards.rasterize_shard`) was given
    wrong arguments; that process's own error names them. ``FLAG``: the name of its device flag
    among the render's finiteness flags, which carry it."""

    FLAG = "another process's arguments"

    def __init__(self):
        super().__init__("another process's arguments to rasterize_shard were wrong (its error says which)")


class CapacityError(RuntimeError):
    """A render binned into ``capacity`` (tile, Gaussian) slots had ``needed`` pairs: its image and
    gradients miss pairs and must be discarded; render again with a capacity of at least ``needed``.
    Raised by :meth:`cdcgs.render.RasterizeInfo.check`."""

    def __init__(self, needed: int, capacity: int):
        self.needed, self.capacity = needed, capacity
        super().__init__(f"the view has {needed} (tile, Gaussian) pairs, more than the capacity {capacity}")
