"""COLMAP scenes: intrinsics, poses, splits, factors, undistortion and every bad input."""

import logging
import os
import re
import struct

import numpy as np
import pytest
import torch
from PIL import Image
from scenes import distorted_line_image, line_residual, project, write_colmap_scene

from cdcgs.errors import InputError, OptionError
from cdcgs.io import load_scene

BONSAI = os.environ.get("CDCGS_BONSAI", os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "bonsai"))


@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_PINHOLE"])
@pytest.mark.parametrize("text", [False, True])
def test_pinhole_scene_poses_and_intrinsics(tmp_path, model, text):
    import pycolmap

    write_colmap_scene(tmp_path, model=model, text=text)
    scene = load_scene(tmp_path, device="cpu", progress=False)
    rec = pycolmap.Reconstruction(os.path.join(tmp_path, "sparse", "0"))
    by_name = {img.name: img for img in rec.images.values()}
    X = np.array([0.1, 0.2, -0.3])
    for view in scene.views:
        # Same pixel through pycolmap's projection (its convention) and ours.
        np.testing.assert_allclose(project(view, X), by_name[view.name].project_point(X), atol=1e-4)
        assert view.image.shape == (48, 64, 3) and view.image.dtype == torch.uint8
    assert scene.source == "colmap" and scene.points.shape == (50, 3) and scene.colors.dtype == torch.uint8


def test_split_every_eighth_by_name(tmp_path):
    write_colmap_scene(tmp_path, n_images=17)
    scene = load_scene(tmp_path, load_images_now=False)
    names = [f"img_{i:03d}.png" for i in range(17)]
    assert [v.name for v in scene.test] == [names[0], names[8], names[16]]
    assert [v.name for v in scene.train] == [n for i, n in enumerate(names) if i % 8]
    scene = load_scene(tmp_path, test_every=4, load_images_now=False)
    assert len(scene.test) == 5 and len(scene.train) == 12
    scene = load_scene(tmp_path, train_on_all=True, load_images_now=False)
    assert len(scene.train) == 17 and len(scene.test) == 3
    scene = load_scene(tmp_path, test_every=0, load_images_now=False)
    assert len(scene.train) == 17 and scene.test == []


def test_named_test_views_stay_the_same_when_a_view_is_missing(tmp_path, caplog):
    # Two models of one capture, one lacking a photo (it did not register): every 8th by name
    # shifts past the gap, the named views do not.
    write_colmap_scene(tmp_path, n_images=17)
    full = load_scene(tmp_path, load_images_now=False)
    listed = tmp_path / "test_views.txt"
    listed.write_text("# held out\n" + "\n".join(v.name for v in full.test) + "\n\n")
    os.remove(tmp_path / "images" / "img_003.png")
    with caplog.at_level(logging.WARNING):
        gap = load_scene(tmp_path, load_images_now=False, skip_missing=True)
    assert [v.name for v in gap.test] == ["img_000.png", "img_009.png"]
    named = load_scene(tmp_path, load_images_now=False, skip_missing=True, test_views=str(listed), test_every=5)
    assert [v.name for v in named.test] == ["img_000.png", "img_008.png", "img_016.png"]
    assert len(named.train) == 13 and not {v.name for v in named.train} & {v.name for v in named.test}
    as_list = load_scene(tmp_path, load_images_now=False, skip_missing=True, test_views=["img_008.png"])
    assert [v.name for v in as_list.test] == ["img_008.png"] and len(as_list.train) == 15


@pytest.mark.parametrize(
    "text, message",
    [
        (None, "no such file of view names"),
        ("# nothing\n\n", "names no view"),
        ("\ufeffimg_001.png\r\nimg_003.png\r\nIMG_001.png\r\n", "2 of the 3 test view names are not views of"),
        ("\ufeffimg_001.png\nimg_002.png\n", None),
    ],
)
def test_bad_test_views_file_is_named(tmp_path, text, message):
    write_colmap_scene(tmp_path, n_images=9)
    os.remove(tmp_path / "images" / "img_003.png")
    listed = tmp_path / "names.txt"
    if text is not None:
        listed.write_text(text)
    if message is None:  # a byte-order mark and CRLF endings are not part of the names
        scene = load_scene(tmp_path, load_images_now=False, skip_missing=True, test_views=listed)
        assert [v.name for v in scene.test] == ["img_001.png", "img_002.png"]
        return
    with pytest.raises(InputError, match=re.escape(message)) as info:
        load_scene(tmp_path, load_images_now=False, skip_missing=True, test_views=listed)
    assert "names.txt" in str(info.value)
    if "not views" in message:
        assert str(info.value).endswith("IMG_001.png, img_003.png")
    good = tmp_path / "good.txt"
    good.write_text("img_001.png\n")
    with pytest.raises(OptionError, match=r"^test_every must be a non-negative int"):  # not the file's fault
        load_scene(tmp_path, load_images_now=False, skip_missing=True, test_views=good, test_every=-1)


def test_extent_is_3dgs_radius(tmp_path):
    _, poses, _ = write_colmap_scene(tmp_path, n_images=16)
    scene = load_scene(tmp_path, load_images_now=False)
    centers = np.array([-p[:3, :3].T @ p[:3, 3] for i, p in enumerate(poses) if i % 8])
    expected = 1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max()
    assert scene.extent == pytest.approx(expected, rel=1e-5)


def test_factor_folder_scales_intrinsics(tmp_path):
    write_colmap_scene(tmp_path, factors=(2,))
    full = load_scene(tmp_path, load_images_now=False)
    half = load_scene(tmp_path, images="images_2", progress=False)
    for a, b in zip(full.views, half.views):
        torch.testing.assert_close(b.K[:2], a.K[:2] * 0.5)
        assert (b.width, b.height) == (32, 24) and b.image.shape == (24, 32, 3)
        X = np.array([0.2, -0.1, 0.1])
        np.testing.assert_allclose(project(b, X), project(a, X) / 2, atol=1e-4)
    assert (
        load_scene(tmp_path, factor=2, load_images_now=False)
        .views[0]
        .image_path.endswith(os.path.join("images_2", "img_000.png"))
    )


def test_missing_factor_folder_resizes_and_says_so_once(tmp_path, caplog):
    write_colmap_scene(tmp_path)
    with caplog.at_level(logging.WARNING, logger="cdcgs"):
        scene = load_scene(tmp_path, images="images_4", progress=False)
    messages = [r.getMessage() for r in caplog.records if "images_4 is missing" in r.getMessage()]
    assert len(messages) == 1
    view = scene.views[3]
    assert (view.width, view.height) == (16, 12) and view.image.shape == (12, 16, 3)
    torch.testing.assert_close(view.K[0, 0], torch.tensor(50.0 * 16 / 64))
    # The content is the full image, resized.
    full = np.asarray(
        Image.open(os.path.join(tmp_path, "images", view.name)).convert("RGB").resize((16, 12), Image.LANCZOS)
    )
    np.testing.assert_array_equal(view.image.numpy(), full)


@pytest.mark.parametrize(
    "model,params",
    [("OPENCV", [90.0, 92.0, 80.0, 60.0, -0.25, 0.08, 0.002, -0.001]), ("SIMPLE_RADIAL", [90.0, 80.0, 60.0, -0.15])],
)
def test_distorted_cameras_are_undistorted_and_cached(tmp_path, model, params):
    width, height = 160, 120
    write_colmap_scene(tmp_path, n_images=3, width=width, height=height, model=model, params=params)
    if model == "OPENCV":
        fx, fy, cx, cy, *dist = params
    else:
        fx, cx, cy, k = params
        fy, dist = fx, [k, 0.0, 0.0, 0.0]
    picture = distorted_line_image(width, height, fx, fy, cx, cy, dist)
    for i in range(3):
        Image.fromarray(picture).save(os.path.join(tmp_path, "images", f"img_{i:03d}.png"))
    assert line_residual(picture[..., 0] > 128) > 1.0, "the distorted line must be visibly curved"
    scene = load_scene(tmp_path, progress=False)
    view = scene.views[0]
    assert "undistorted" in view.image_path
    straight = view.image[..., 0].numpy() > 128
    assert straight.sum() > 100
    assert line_residual(straight) < 0.6
    # Cached: a second load reuses the undistorted images without rewriting them.
    mtime = os.path.getmtime(view.image_path)
    again = load_scene(tmp_path, progress=False)
    assert again.views[0].image_path == view.image_path and os.path.getmtime(view.image_path) == mtime
    torch.testing.assert_close(again.views[0].image, view.image)


# ----------------------------------------------------------------------------------- bad input


def test_missing_scene_folder(tmp_path):
    with pytest.raises(InputError, match="no such scene folder") as err:
        load_scene(tmp_path / "nope")
    assert err.value.path == str(tmp_path / "nope")


def test_folder_without_model(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(InputError, match="no COLMAP model"):
        load_scene(tmp_path)


def test_unreadable_model(tmp_path):
    write_colmap_scene(tmp_path)
    with open(tmp_path / "sparse" / "0" / "images.bin", "wb") as f:
        f.write(b"\x07garbage")
    with pytest.raises(InputError, match=r"images\.bin: is truncated or not a COLMAP file"):
        load_scene(tmp_path)
    # Sizes that pass the check, content that pycolmap refuses: its error, with the folder named.
    write_colmap_scene(tmp_path / "b")
    with open(tmp_path / "b" / "sparse" / "0" / "cameras.bin", "wb") as f:
        f.write(struct.pack("<QiiQQd", 1, 1, 999, 64, 48, 50.0))
    with pytest.raises(InputError, match="sparse/0: cannot read the COLMAP model"):
        load_scene(tmp_path / "b")


def test_missing_images_refused_or_skipped(tmp_path, caplog):
    write_colmap_scene(tmp_path)
    os.remove(tmp_path / "images" / "img_003.png")
    os.remove(tmp_path / "images" / "img_007.png")
    with pytest.raises(InputError, match=r"2 of 10 images .* missing.*img_003.png"):
        load_scene(tmp_path)
    with caplog.at_level(logging.WARNING, logger="cdcgs"):
        scene = load_scene(tmp_path, skip_missing=True, progress=False)
    assert len(scene.views) == 8 and any("skipping" in r.getMessage() for r in caplog.records)


def test_image_of_wrong_size(tmp_path):
    write_colmap_scene(tmp_path, factors=(2,))
    Image.fromarray(np.zeros((20, 20, 3), np.uint8)).save(tmp_path / "images_2" / "img_004.png")
    with pytest.raises(InputError, match="image is 20x20 but its camera") as err:
        load_scene(tmp_path, images="images_2")
    assert err.value.path.endswith("img_004.png")


def test_missing_image_folder(tmp_path):
    write_colmap_scene(tmp_path, with_images=False)
    with pytest.raises(InputError, match="no such image folder"):
        load_scene(tmp_path, images="images_8")


def test_unreadable_image(tmp_path):
    write_colmap_scene(tmp_path)
    (tmp_path / "images" / "img_002.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="cannot read the image") as err:
        load_scene(tmp_path)
    assert err.value.path.endswith("img_002.png")


def test_inconsistent_folder_and_factor(tmp_path):
    write_colmap_scene(tmp_path)
    with pytest.raises(ValueError, match="implies factor 4"):
        load_scene(tmp_path, images="images_4", factor=2)


@pytest.mark.skipif(not os.path.isdir(BONSAI), reason="../shared/data/bonsai is absent")
def test_bonsai_loads_with_correct_poses(tmp_path):
    import pycolmap

    scene = load_scene(BONSAI, images="images_4", load_images_now=False)
    assert len(scene.train) == 255 and len(scene.test) == 37
    assert (scene.train[0].width, scene.train[0].height) == (200, 133)
    rec = pycolmap.Reconstruction(os.path.join(BONSAI, "sparse", "0"))
    by_name = {img.name: img for img in rec.images.values()}
    errors = []
    for view in scene.views[::40]:
        image = by_name[view.name]
        sx, sy = 800 / view.width, 533 / view.height
        for point2d in image.points2D:
            if point2d.has_point3D():
                pixel = project(view, rec.points3D[point2d.point3D_id].xyz)
                errors.append(np.hypot(pixel[0] * sx - point2d.xy[0], pixel[1] * sy - point2d.xy[1]))
    assert len(errors) > 1000
    assert np.mean(errors) < 1.0, f"mean reprojection error {np.mean(errors):.3f} px at full size"


def test_read_only_scene_caches_in_user_folder(tmp_path, monkeypatch):
    import cdcgs.io.colmap as colmap

    scene_dir = tmp_path / "scene"
    write_colmap_scene(
        scene_dir, n_images=2, width=80, height=60, model="SIMPLE_RADIAL", params=[60.0, 40.0, 30.0, -0.2]
    )
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    # Root can write anywhere, so read-only is simulated: nothing under the scene is writable.
    writable = colmap._writable
    monkeypatch.setattr(
        colmap, "_writable", lambda folder: not str(folder).startswith(str(scene_dir)) and writable(folder)
    )
    scene = load_scene(scene_dir, progress=False)
    assert scene.views[0].image_path.startswith(str(tmp_path / "cache" / "cdcgs"))
    assert not (scene_dir / ".cdcgs_cache").exists()


@pytest.mark.parametrize(
    "damage,message",
    [
        (lambda d: open(os.path.join(d, "points3D.bin"), "wb").close(), "points3D.bin: is empty (0 bytes)"),
        (lambda d: os.remove(os.path.join(d, "images.bin")), "images.bin: missing"),
        (lambda d: _truncate(os.path.join(d, "images.bin"), 40), "images.bin: is truncated or not a COLMAP file"),
        (lambda d: _truncate(os.path.join(d, "cameras.bin"), 5), "cameras.bin: is truncated (5 bytes"),
        (
            lambda d: _overwrite(os.path.join(d, "points3D.bin"), b"\xff" * 64),
            "points3D.bin: is truncated or not a COLMAP file",
        ),
    ],
)
def test_broken_model_files_are_named_before_pycolmap_reads_them(tmp_path, damage, message):
    import time

    write_colmap_scene(tmp_path)
    damage(str(tmp_path / "sparse" / "0"))
    start = time.perf_counter()
    with pytest.raises(InputError, match=re.escape(message)):
        load_scene(tmp_path, load_images_now=False)
    assert time.perf_counter() - start < 5.0


def _truncate(path, size):
    with open(path, "r+b") as f:
        f.truncate(size)


def _overwrite(path, data):
    with open(path, "wb") as f:
        f.write(data)


def test_a_model_without_points_needs_random_init(tmp_path, caplog):
    write_colmap_scene(tmp_path, points=np.zeros((0, 3)))
    with pytest.raises(InputError, match="has no 3D points to start from; pass --random-init"):
        load_scene(tmp_path, load_images_now=False)
    scene = load_scene(tmp_path, load_images_now=False, random_init=True)
    assert scene.points.shape[0] > 0 and "random initial points" in scene.notes[-1]
    assert "--random-init" in caplog.text


@pytest.mark.parametrize(
    "params,message",
    [
        ([1e20, 52.0, 31.5, 24.2], "focal length fx = 1e+20 px is not plausible for an image 64 px across"),
        ([50.0, 0.0, 31.5, 24.2], "focal length fy = 0 px is not plausible"),
        ([50.0, 52.0, 5000.0, 24.2], "principal point cx = 5000 px lies far outside the 64 px image"),
    ],
)
def test_implausible_intrinsics_are_refused_at_load(tmp_path, params, message):
    write_colmap_scene(tmp_path, params=params)
    with pytest.raises(InputError, match=re.escape(message)):
        load_scene(tmp_path, load_images_now=False)
