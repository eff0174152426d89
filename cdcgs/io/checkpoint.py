"""Checkpoints of a whole training state, written atomically.

A checkpoint is one ``torch.save`` file of a dict (parameters, optimizer moments, strategy state,
step, the run's random generator states, config as plain data) with a SHA-256 of that content
(``checksum``: every tensor's dtype, shape and bytes, every other value's repr, in key order),
which :func:`load_checkpoint` checks, so flipped bytes inside tensor data are found. It is written
to a temporary file in the same folder, flushed to disk, then renamed over the old one, so a crash
or a full disk while saving leaves the previous checkpoint intact.
"""

from __future__ import annotations

import glob
import hashlib
import os
import pickle
import zipfile

import torch

from ..errors import InputError

__all__ = ["content_checksum", "load_checkpoint", "remove_temporary_files", "save_checkpoint"]

CHECKSUM = "checksum"


def content_checksum(state) -> str:
    """SHA-256 of a checkpoint's content: tensors by dtype, shape and bytes, other values by repr,
    dicts in key order (the ``checksum`` entry itself left out)."""
    digest = hashlib.sha256()

    def feed(value):
        if isinstance(value, torch.Tensor):
            tensor = value.detach().cpu().contiguous()
            digest.update(f"T{tensor.dtype}{list(tensor.shape)}".encode())
            digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
        elif isinstance(value, dict):
            digest.update(b"{")
            for key in sorted(value, key=repr):
                if key != CHECKSUM:
                    digest.update(repr(key).encode())
                    feed(value[key])
            digest.update(b"}")
        elif isinstance(value, (list, tuple)):
            digest.update(b"[")
            for item in value:
                feed(item)
            digest.update(b"]")
        else:
            digest.update(repr(value).encode())

    feed(state)
    return digest.hexdigest()


def remove_temporary_files(path) -> int:
    """Remove what interrupted writes of the checkpoint ``path`` left behind; how many. Only for
    the holder of the run folder's lock (nobody else is writing)."""
    path = os.fspath(path)
    pattern = os.path.join(os.path.dirname(os.path.abspath(path)), f".{os.path.basename(path)}.tmp-*")
    leftovers = glob.glob(pattern)
    for leftover in leftovers:
        os.remove(leftover)
    return len(leftovers)


def save_checkpoint(path, state: dict) -> None:
    """Write ``state`` and its checksum to ``path`` atomically (temporary file, fsync, rename).

    Raises:
        InputError: the file could not be written (a full disk, no permission); the previous
            checkpoint is intact.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.tmp-{os.getpid()}")
    state = {**state, CHECKSUM: content_checksum(state)}
    try:
        try:
            with open(tmp, "wb") as f:
                torch.save(state, f)
                f.flush()
                os.fsync(f.fileno())
        except OSError as err:
            intact = "the previous checkpoint is intact" if os.path.isfile(path) else "there was no previous checkpoint"
            raise InputError(path, f"could not write the checkpoint ({err.strerror or err}); {intact}") from None
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
        InputError: the file is missing, unreadable, truncated, not a cdcgs checkpoint, or its
            content does not match its checksum (checkpoints written before checksums have none).
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
    if CHECKSUM in state and content_checksum(state) != state[CHECKSUM]:
        raise InputError(path, "the checkpoint's content does not match its checksum: the file is damaged")
    return state
