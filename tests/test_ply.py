"""Gaussian PLY export/import: bit-exact round trip, the INRIA layout, damaged files."""

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cdcgs.errors import InputError
from cdcgs.io import GaussianPly, read_ply, write_ply


def random_model(n=37, degree=3, seed=0) -> GaussianPly:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return GaussianPly(
        means=torch.randn(n, 3, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 4,
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, k, 3, generator=g),
    )


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_bit_exact(tmp_path, degree):
    model = random_model(degree=degree)
    write_ply(tmp_path / "m.ply", model)
    back = read_ply(tmp_path / "m.ply")
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(back, name), getattr(model, name)), name
    assert back.sh_degree == degree


def test_layout_matches_inria(tmp_path):
    """Read back with plyfile (an independent reader): names, order and channel-major f_rest."""
    from plyfile import PlyData

    model = random_model(n=5, degree=2)
    write_ply(tmp_path / "m.ply", model)
    ply = PlyData.read(str(tmp_path / "m.ply"))
    assert ply.elements[0].name == "vertex" and ply.elements[0].count == 5
    names = [p.name for p in ply.elements[0].properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:33] == [f"f_rest_{i}" for i in range(24)]
    assert names[33:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    v = ply["vertex"]
    assert ply.byte_order == "<" and all(p.val_dtype in ("f4", "float32") for p in ply.elements[0].properties)
    # f_rest_{c * 8 + j} is channel c of coefficient j + 1 (channel-major, INRIA's order).
    for c in range(3):
        for j in range(8):
            np.testing.assert_array_equal(v[f"f_rest_{c * 8 + j}"], model.sh[:, j + 1, c].numpy())
    np.testing.assert_array_equal(v["rot_0"], model.quats[:, 0].numpy())
    np.testing.assert_array_equal(v["opacity"], model.opacity_logits.numpy())


@pytest.mark.parametrize("normals", [True, False])
def test_reads_a_file_written_by_plyfile(tmp_path, normals):
    """A PLY written by another tool in the standard layout opens (here: degree 1, plyfile), with
    the normals 3DGS writes or without them (gsplat's export), fields in another order."""
    from plyfile import PlyData, PlyElement

    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(9)] + [
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    if not normals:
        names = names[::-1]
    data = np.zeros(4, dtype=[(n, "f4") for n in names])
    for i, n in enumerate(names):
        data[n] = np.arange(4) + 10 * i
    PlyData([PlyElement.describe(data, "vertex")], byte_order="<").write(str(tmp_path / "other.ply"))
    model = read_ply(tmp_path / "other.ply")
    assert model.sh.shape == (4, 4, 3)
    np.testing.assert_array_equal(model.sh[:, 1, 0].numpy(), data["f_rest_0"])
    np.testing.assert_array_equal(model.sh[:, 1, 1].numpy(), data["f_rest_3"])
    np.testing.assert_array_equal(model.quats[:, 3].numpy(), data["rot_3"])
    np.testing.assert_array_equal(model.means[:, 1].numpy(), data["y"])
    np.testing.assert_array_equal(model.opacity_logits.numpy(), data["opacity"])


def test_non_finite_values_are_never_written(tmp_path):
    model = random_model()
    model.opacity_logits[2] = float("nan")
    with pytest.raises(ValueError, match=r"not written: 1 Gaussian\(s\) have NaN or infinite opacity_logits"):
        write_ply(tmp_path / "nan.ply", model)
    assert not (tmp_path / "nan.ply").exists()


def test_non_finite_values_are_refused(tmp_path):
    model = random_model()
    model.log_scales[3, 1] = 12345.0  # markers, replaced by NaN and inf in the file's bytes
    model.means[5, 0] = 54321.0
    write_ply(tmp_path / "nan.ply", model)
    data = (tmp_path / "nan.ply").read_bytes()
    for marker, bad in ((12345.0, float("nan")), (54321.0, float("inf"))):
        data = data.replace(np.float32(marker).tobytes(), np.float32(bad).tobytes())
    (tmp_path / "nan.ply").write_bytes(data)
    with pytest.raises(InputError, match=r"2 of .* vertices hold NaN or infinite values \(the first is vertex 3\)"):
        read_ply(tmp_path / "nan.ply")


@pytest.mark.parametrize(
    "damage,match",
    [
        (lambda b: b[: len(b) - 7], "truncated"),
        (lambda b: b + b"\0" * 4, "longer than its header"),
        (lambda b: b.replace(b"property float opacity\n", b""), "missing \\['opacity'\\]"),
        (lambda b: b.replace(b"property float scale_0\n", b"property float scale_9\n"), "missing \\['scale_0'\\]"),
        (lambda b: b.replace(b"f_rest_44", b"f_rest_XX"), "missing \\['f_rest_44'\\]"),
        (
            lambda b: b.replace(b"property float scale_1\n", b"property float scale_0\n"),
            "names a vertex property twice|missing",
        ),
        (lambda b: b.replace(b"property float f_rest_44\n", b""), "44 f_rest fields"),
        (lambda b: b.replace(b"binary_little_endian", b"ascii"), "format 'ascii'"),
        (lambda b: b.replace(b"element vertex 37", b"element vertex 38"), "truncated"),
        (lambda b: b"PLY?" + b[4:], "not a PLY file"),
        (lambda b: b.replace(b"end_header\n", b"end_headr\n"), "never ends|unknown PLY header line"),
        (lambda b: b.replace(b"property float x\n", b"property double x\n"), "not a float32 scalar"),
    ],
)
def test_damaged_files_fail_clearly(tmp_path, damage, match):
    write_ply(tmp_path / "m.ply", random_model())
    broken = tmp_path / "broken.ply"
    broken.write_bytes(damage((tmp_path / "m.ply").read_bytes()))
    with pytest.raises(InputError, match=match) as err:
        read_ply(broken)
    assert err.value.path == str(broken)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="cannot open the PLY file"):
        read_ply(tmp_path / "none.ply")


def test_write_is_atomic_and_checks_shapes(tmp_path):
    model = random_model()
    write_ply(tmp_path / "m.ply", model)
    before = (tmp_path / "m.ply").read_bytes()
    bad = GaussianPly(model.means, model.log_scales, model.quats[:, :3], model.opacity_logits, model.sh)
    with pytest.raises(ValueError, match="quats must have shape"):
        write_ply(tmp_path / "m.ply", bad)
    assert (tmp_path / "m.ply").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]


_ORIGINAL = {}


def _original_bytes(tmp_path_factory):
    if "bytes" not in _ORIGINAL:
        path = tmp_path_factory.mktemp("ply") / "m.ply"
        write_ply(path, random_model(n=6, degree=1))
        _ORIGINAL["bytes"] = path.read_bytes()
    return _ORIGINAL["bytes"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzzed_files_raise_only_input_error(tmp_path_factory, data):
    """Damaged files (cut, spliced, flipped bytes, garbage) are refused with InputError or read."""
    original = _original_bytes(tmp_path_factory)
    kind = data.draw(st.sampled_from(["cut", "flip", "insert", "garbage", "header_edit"]))
    if kind == "cut":
        damaged = original[: data.draw(st.integers(0, len(original)))]
    elif kind == "flip":
        pos = data.draw(st.integers(0, len(original) - 1))
        damaged = original[:pos] + bytes([original[pos] ^ data.draw(st.integers(1, 255))]) + original[pos + 1 :]
    elif kind == "insert":
        pos = data.draw(st.integers(0, len(original)))
        damaged = original[:pos] + data.draw(st.binary(min_size=1, max_size=16)) + original[pos:]
    elif kind == "garbage":
        damaged = data.draw(st.binary(max_size=600))
    else:
        header_end = original.index(b"end_header\n")
        pos = data.draw(st.integers(0, header_end))
        damaged = (
            original[:pos] + data.draw(st.sampled_from([b"\n", b" ", b"element face 3\n", b"x", b"9"])) + original[pos:]
        )
    path = tmp_path_factory.mktemp("fuzz") / "f.ply"
    path.write_bytes(damaged)
    try:
        model = read_ply(path)
    except InputError:
        return
    assert model.means.shape[1] == 3 and model.sh.shape[0] == model.means.shape[0]
