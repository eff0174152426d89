"""Gaussian models as PLY files in the layout of the INRIA 3DGS release.

Properties, all float32, binary little endian, in this order:
x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3, where K = (degree+1)^2,
f_rest is channel-major (all of red's higher-order coefficients, then green's, then blue's),
opacity is a logit, scales are logs and the quaternion is w x y z. SuperSplat, gsplat and most
viewers read this. Export then import is bit-exact.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError

__all__ = ["GaussianPly", "read_ply", "write_ply"]


@dataclass
class GaussianPly:
    """Gaussian parameters as stored (pre-activation), float32 CPU or device tensors.

    means [N, 3]; log_scales [N, 3]; quats [N, 4] (w, x, y, z, not necessarily unit);
    opacity_logits [N]; sh [N, K, 3] with K = (degree + 1)^2, the DC term first.
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor

    @property
    def sh_degree(self) -> int:
        return math.isqrt(self.sh.shape[1]) - 1


def _property_names(num_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(num_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_ply(path, model: GaussianPly) -> None:
    """Write ``model`` to ``path`` (binary little endian), atomically (temporary file, then rename)."""
    n = model.means.shape[0]
    k = model.sh.shape[1]
    if (math.isqrt(k) ** 2) != k or k > 16:
        raise ValueError(f"sh must have (degree+1)^2 <= 16 coefficients per channel, got {k}")
    shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,), "sh": (n, k, 3)}
    for name, shape in shapes.items():
        value = getattr(model, name)
        if tuple(value.shape) != shape:
            raise ValueError(f"{name} must have shape {list(shape)}, got {list(value.shape)}")
        if not torch.isfinite(value).all():
            bad = int((~torch.isfinite(value)).reshape(n, -1).any(-1).sum()) if n else 0
            raise ValueError(f"{path}: not written: {bad} Gaussian(s) have NaN or infinite {name}")
    cpu = lambda t: t.detach().to("cpu", torch.float32).numpy()
    sh = cpu(model.sh)
    columns = [
        cpu(model.means),
        np.zeros((n, 3), np.float32),
        sh[:, 0, :],
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)),  # channel-major, as INRIA writes it
        cpu(model.opacity_logits)[:, None],
        cpu(model.log_scales),
        cpu(model.quats),
    ]
    data = np.ascontiguousarray(np.concatenate(columns, axis=1), dtype="<f4")
    names = _property_names(3 * (k - 1))
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"element vertex {n}\n" + "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path = os.fspath(path)
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(data.tobytes())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


NORMALS = ("nx", "ny", "nz")  # written by 3DGS (zeros), left out by some tools; never read


def _parse_header(path: str, f) -> tuple[int, list[str], int]:
    first = f.readline(64)
    if first.rstrip(b"\r\n") != b"ply":
        raise InputError(path, "not a PLY file (it does not start with 'ply')")
    count = None
    names: list[str] = []
    fmt = None
    in_vertex = False
    for _ in range(10_000):
        raw = f.readline(1024)
        if not raw:
            raise InputError(path, "the PLY header never ends (no 'end_header')")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise InputError(path, "the PLY header holds non-ASCII bytes") from None
        if line == "end_header":
            break
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else None
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(path, f"malformed element line {line!r}")
            if words[1] == "vertex":
                if count is not None:
                    raise InputError(path, "the PLY header declares 'vertex' twice")
                count, in_vertex = int(words[2]), True
            else:
                if int(words[2]) != 0:
                    raise InputError(path, f"unexpected element {words[1]!r}: a Gaussian PLY holds only vertices")
                in_vertex = False
        elif words[0] == "property":
            if not in_vertex:
                raise InputError(path, f"property outside the vertex element: {line!r}")
            if len(words) != 3 or words[1] not in ("float", "float32"):
                raise InputError(path, f"property {line!r} is not a float32 scalar; Gaussian PLYs hold only floats")
            names.append(words[2])
        else:
            raise InputError(path, f"unknown PLY header line {line!r}")
    else:
        raise InputError(path, "the PLY header is too long")
    if fmt != "binary_little_endian":
        raise InputError(path, f"format {fmt!r} is not supported; Gaussian PLYs are binary_little_endian")
    if count is None:
        raise InputError(path, "the PLY header declares no vertex element")
    return count, names, f.tell()


def read_ply(path, device="cpu") -> GaussianPly:
    """Read a Gaussian PLY in the INRIA layout (as written by 3DGS, gsplat, SuperSplat, cdcgs).

    Raises:
        InputError: the file is missing or unreadable, is not a binary little-endian PLY, lacks a
            field of the layout (fields are found by name; extra float fields such as normals are
            ignored), has a spherical-harmonics count that is not (d+1)^2 - 1 per channel, its
            body is shorter or longer than the header says, or a value is NaN or infinite.
    """
    path = os.fspath(path)
    try:
        f = open(path, "rb")  # noqa: SIM115  (closed by the with below; only opening errors are caught here)
    except OSError as err:
        raise InputError(path, f"cannot open the PLY file: {err.strerror}") from None
    with f:
        count, names, _ = _parse_header(path, f)
        num_rest = sum(name.startswith("f_rest_") for name in names)
        if num_rest % 3 != 0 or math.isqrt(num_rest // 3 + 1) ** 2 != num_rest // 3 + 1 or num_rest > 45:
            raise InputError(path, f"{num_rest} f_rest fields: expected 3 x ((degree+1)^2 - 1) for degree 0..3")
        expected = _property_names(num_rest)
        missing = [n for n in expected if n not in names and n not in NORMALS]
        if missing:
            raise InputError(path, f"vertex properties are not the 3DGS layout: missing {missing}")
        if len(set(names)) != len(names):
            raise InputError(path, "the PLY header names a vertex property twice")
        row = 4 * len(names)
        body = f.read()
    if len(body) != count * row:
        what = "truncated" if len(body) < count * row else "longer than its header says"
        raise InputError(path, f"the body is {what}: {len(body)} bytes for {count} vertices of {row} bytes")
    # Fields are found by name, so other tools' orders and extra fields (normals nx ny nz, which
    # gsplat and SuperSplat may leave out or add) are fine.
    table = np.frombuffer(body, dtype="<f4").reshape(count, len(names))
    zeros = np.zeros(count, np.float32)
    data = np.stack([table[:, names.index(n)] if n in names else zeros for n in expected], axis=1)
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        raise InputError(
            path,
            f"{int(bad.sum())} of {count} vertices hold NaN or infinite values (the first is vertex {int(np.argmax(bad))})",
        )
    k = num_rest // 3 + 1
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device)
    sh = np.empty((count, k, 3), np.float32)
    sh[:, 0, :] = data[:, 6:9]
    sh[:, 1:, :] = data[:, 9 : 9 + num_rest].reshape(count, 3, k - 1).transpose(0, 2, 1)
    tail = 9 + num_rest
    return GaussianPly(
        means=t(data[:, 0:3]),
        opacity_logits=t(data[:, tail]),
        log_scales=t(data[:, tail + 1 : tail + 4]),
        quats=t(data[:, tail + 4 : tail + 8]),
        sh=t(sh),
    )
