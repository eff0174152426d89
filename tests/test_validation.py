"""Bad input gets a ValueError that names the argument, never a crash inside a kernel."""

import pytest
import torch
from conftest import make_scene

import cdcgs


@pytest.fixture
def args(device):
    scene = make_scene(20, 24, 16, sh_degree=1, seed=8, hard_cases=False)
    tensors = dict(zip(["means", "quats", "scales", "opacities", "sh"], [t.to(device) for t in scene.tensors()]))
    return tensors, dict(viewmat=scene.viewmat, K=scene.K, width=24, height=16)


def call(tensors, camera, **overrides):
    kwargs = {**tensors, **camera, **overrides}
    return cdcgs.rasterize(**kwargs)


def test_valid_call_renders(args):
    image, _, _ = call(*args)
    assert image.shape == (16, 24, 3) and torch.isfinite(image).all()


@pytest.mark.parametrize(
    "name,bad,match",
    [
        ("means", lambda t: t[:, :2], r"means must have shape \[N, 3\]"),
        ("quats", lambda t: t[:-1], r"quats must have shape \[20, 4\]"),
        ("scales", lambda t: t.double(), "scales must be float32"),
        ("opacities", lambda t: t[:, None], r"opacities must have shape \[20\]"),
        ("sh", lambda t: t[:, :3], "sh has 3 coefficients"),
        ("means", lambda t: t.numpy(force=True), "means must be a torch.Tensor"),
        ("opacities", lambda t: t.half(), "opacities must be float32"),
    ],
)
def test_wrong_shapes_and_dtypes(args, name, bad, match):
    tensors, camera = args
    with pytest.raises(ValueError, match=match):
        call({**tensors, name: bad(tensors[name])}, camera)


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "sh"])
@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_values(args, name, value):
    tensors, camera = args
    broken = tensors[name].clone()
    broken.view(-1)[3] = value
    with pytest.raises(ValueError, match=f"{name} has non-finite values"):
        call({**tensors, name: broken}, camera)


def test_sh_is_checked_where_it_is_read(args):
    """The colouring kernel validates ``sh`` as it reads it: a NaN in a Gaussian in view raises, one
    in a culled Gaussian (never read, never in the image) does not change the render."""
    tensors, camera = args
    opacities = tensors["opacities"].clone()
    opacities[5] = 0.0  # cannot reach alpha 1/255: culled
    tensors = {**tensors, "opacities": opacities}
    image, _, info = call(tensors, camera)
    assert not info.visible[5] and info.visible[6]
    for g, raises in ((5, False), (6, True)):
        broken = tensors["sh"].clone()
        broken[g, 1, 2] = float("nan")
        if raises:
            with pytest.raises(ValueError, match="sh has non-finite values"):
                call({**tensors, "sh": broken}, camera)
        else:
            assert torch.equal(call({**tensors, "sh": broken}, camera)[0], image)


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "sh", "colors"])
def test_non_finite_last_value_is_found(args, name):
    """The check runs one thread per value of the longest input; every input's last value counts
    (``sh``'s in the colouring kernel: its last Gaussian is in view)."""
    tensors, camera = args
    if name == "colors":
        tensors = {**{k: v for k, v in tensors.items() if k != "sh"}, "colors": torch.rand_like(tensors["means"])}
    if name == "sh":
        assert call(tensors, camera)[2].visible[-1]
    broken = tensors[name].clone()
    broken.view(-1)[-1] = -float("inf")
    with pytest.raises(ValueError, match=f"{name} has non-finite values"):
        call({**tensors, name: broken}, camera)


def test_cameras_are_checked_on_every_call(args):
    """Without a PreparedCamera the matrices are read on every call: a moved camera renders anew,
    and a matrix that was fine before is checked again once broken."""
    tensors, camera = args
    first = cdcgs.prepare_camera(camera["viewmat"], camera["K"], 24, 16)
    moved = camera["viewmat"].clone()
    moved[0, 3] += 0.5
    other = cdcgs.prepare_camera(moved, camera["K"], 24, 16)
    assert other.camera.translation[0] == pytest.approx(first.camera.translation[0] + 0.5)
    image_moved = call(tensors, {**camera, "viewmat": moved})[0]
    image = call(tensors, camera)[0]
    assert not torch.equal(image, image_moved)
    bad = camera["viewmat"].clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="viewmat has non-finite entries"):
        call(tensors, {**camera, "viewmat": bad})


def test_non_finite_background(args):
    tensors, camera = args
    with pytest.raises(ValueError, match="background has non-finite"):
        call(tensors, camera, background=torch.tensor([0.0, float("nan"), 0.0], device=tensors["means"].device))


def test_mixed_devices(args):
    tensors, camera = args
    other = "cpu" if tensors["means"].device.type != "cpu" else "meta"
    with pytest.raises(ValueError, match=r"scales is on .* but means is on"):
        call({**tensors, "scales": tensors["scales"].to(other)}, camera)


def test_empty_scene(args):
    tensors, camera = args
    empty = {k: v[:0] for k, v in tensors.items()}
    with pytest.raises(ValueError, match="means is empty"):
        call(empty, camera)


@pytest.mark.parametrize(
    "override,match",
    [
        (dict(width=0), "width must be a positive int"),
        (dict(height=-3), "height must be a positive int"),
        (dict(width=24.0), "width must be a positive int"),
        (dict(viewmat=torch.eye(3)), r"viewmat must have shape \[4, 4\]"),
        (dict(viewmat=torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0]))), "must be a rotation"),
        (dict(viewmat=torch.full((4, 4), float("nan"))), "viewmat has non-finite"),
        (dict(K=torch.zeros(3, 3)), "K must have positive focal lengths"),
        (dict(K="camera"), "K must be a 3x3 matrix"),
        (dict(near_plane=0.0), "near_plane must be a positive"),
        (dict(sh_degree=4), "sh_degree must be an int in 0..3"),
        (dict(sh_degree=2), "degree 2 needs 9"),
        (dict(background=[0.0, 1.0]), "background must have 3 entries"),
        (dict(background="white"), "background must be 3 numbers"),
    ],
)
def test_bad_camera_and_options(args, override, match):
    tensors, camera = args
    with pytest.raises(ValueError, match=match):
        call(tensors, camera, **override)


def test_both_or_neither_of_sh_and_colors(args):
    tensors, camera = args
    with pytest.raises(ValueError, match="exactly one of sh"):
        call(tensors, camera, colors=torch.zeros(20, 3, device=tensors["means"].device))
    without_sh = {k: v for k, v in tensors.items() if k != "sh"}
    with pytest.raises(ValueError, match="exactly one of sh"):
        call(without_sh, camera)


def test_camera_accepts_numpy_and_lists(args):
    tensors, camera = args
    image, _, _ = call(tensors, camera)
    image_np, _, _ = call(tensors, dict(camera, viewmat=camera["viewmat"].numpy(), K=camera["K"].tolist()))
    torch.testing.assert_close(image, image_np)


def test_nothing_visible_renders_background(args):
    tensors, camera = args
    view = camera["viewmat"].to(tensors["means"].device)
    center, forward = -view[:3, :3].T @ view[:3, 3], view[2, :3]
    behind = dict(tensors, means=center - 2.0 * forward + 0.1 * tensors["means"])
    image, alpha, info = call(behind, camera, background=[0.25, 0.5, 0.75])
    assert info.num_intersections == 0 and not info.visible.any()
    torch.testing.assert_close(image, torch.tensor([0.25, 0.5, 0.75], device=image.device).expand(16, 24, 3))
    assert (alpha == 0).all()
