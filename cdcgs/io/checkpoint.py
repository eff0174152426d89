"""Checkpoints of a whole training state, written atomically.

A checkpoint is one ``torch.save`` file of a dict (parameters, optimizer moments, strategy state,
step, the run's random generator states, config as plain data). It is written to a temporary file in the
same folder, flushed to disk, then renamed over the old one, so a crash while saving leaves the
previous checkpoint intact.
"""

from __future__ import annotations

import os
import pickle
import zipfile

import torch

from ..errors import InputError

__all__ = ["load_checkpoint", "save_checkpoint"]


def save_checkpoint(path, state: dict) -> None:
    """Write ``state`` to ``path`` atomically (temporary file, fsync, rename)."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        # Make the rename itself durable.
        dir_fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def load_checkpoint(path, map_location="cpu") -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises:
        InputError: the file is missing, unreadable, truncated or not a cdcgs checkpoint.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(path, "no checkpoint file here")
    try:
        state = torch.load(path, map_location=map_location, weights_only=False)
    except (OSError, EOFError, RuntimeError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError) as err:
        raise InputError(path, f"not a readable checkpoint ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict):
        raise InputError(path, f"not a cdcgs checkpoint (holds a {type(state).__name__}, not a dict)")
    return state
