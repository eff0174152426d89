"""Checkpoints of a whole training state, written atomically.

A checkpoint is one ``torch.save`` file of a dict (parameters, optimizer moments, strategy state,
step, random generator states, config as plain data). It is written to a temporary file in the
same folder, flushed to disk, then renamed over the old one, so a crash while saving leaves the
previous checkpoint intact.
"""

from __future__ import annotations

import os
import pickle
import random
import zipfile

import numpy as np
import torch

from ..errors import InputError

__all__ = ["capture_rng_state", "load_checkpoint", "restore_rng_state", "save_checkpoint"]


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


def capture_rng_state() -> dict:
    """The states of Python's, numpy's and torch's (CPU and every CUDA device) generators."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict) -> None:
    """Put back generator states captured by :func:`capture_rng_state`."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
