"""transforms.json scenes: OpenGL poses converted once, intrinsics, distortion, points, bad input."""

import json
import logging
import os

import numpy as np
import pytest
import torch
from PIL import Image
from scenes import distorted_line_image, line_residual, project, write_transforms_scene

from cdcgs.errors import InputError
from cdcgs.io import load_scene


def test_opengl_poses_become_world_to_camera(tmp_path):
    _, poses = write_transforms_scene(tmp_path)
    scene = load_scene(tmp_path, progress=False)
    assert scene.source == "transforms" and len(scene.views) == 10
    X = np.array([0.2, -0.1, 0.3])
    for view, w2c in zip(scene.views, poses):
        torch.testing.assert_close(view.viewmat, torch.from_numpy(w2c).float(), atol=1e-6, rtol=0)
        cam = w2c[:3, :3] @ X + w2c[:3, 3]
        expected = np.array([45.0 * cam[0] / cam[2] + 20.5, 46.0 * cam[1] / cam[2] + 14.0])
        np.testing.assert_allclose(project(view, X), expected, atol=1e-4)
        assert view.image.shape == (30, 40, 3)
    # The scene centre is in front of every camera (z forward): the conversion kept handedness.
    for view in scene.views:
        assert (view.viewmat[:3, :3] @ torch.zeros(3) + view.viewmat[:3, 3])[2] > 0


def test_per_frame_intrinsics(tmp_path):
    write_transforms_scene(tmp_path, per_frame=True)
    scene = load_scene(tmp_path, test_every=0, load_images_now=False)
    for i, view in enumerate(scene.views):
        torch.testing.assert_close(view.K, torch.tensor([[40.0 + i, 0, 19.5], [0, 41.0 + i, 15.25], [0, 0, 1]]))


def test_camera_angle_x_and_factor(tmp_path):
    write_transforms_scene(tmp_path, angle=True)
    scene = load_scene(tmp_path, factor=2, progress=False)
    f = 0.5 * 40 / np.tan(0.6)
    view = scene.views[0]
    assert (view.width, view.height) == (20, 15) and view.image.shape == (15, 20, 3)
    torch.testing.assert_close(
        view.K, torch.tensor([[f / 2, 0, 10.0], [0, f / 2, 7.5], [0, 0, 1]], dtype=torch.float32)
    )


def test_distortion_is_undistorted(tmp_path):
    width, height, f, cx, cy = 160, 120, 90.0, 80.0, 60.0
    dist = (-0.25, 0.08, 0.002, -0.001)
    write_transforms_scene(
        tmp_path,
        n_images=2,
        width=width,
        height=height,
        extra={"k1": dist[0], "k2": dist[1], "p1": dist[2], "p2": dist[3]},
    )
    meta = json.load(open(tmp_path / "transforms.json"))
    meta.update(fl_x=f, fl_y=f, cx=cx, cy=cy)
    json.dump(meta, open(tmp_path / "transforms.json", "w"))
    picture = distorted_line_image(width, height, f, f, cx, cy, dist)
    for i in range(2):
        Image.fromarray(picture).save(tmp_path / "images" / f"frame_{i:03d}.png")
    assert line_residual(picture[..., 0] > 128) > 1.0
    view = load_scene(tmp_path, progress=False, test_every=0).views[0]
    assert view.image.shape == (view.height, view.width, 3)
    assert line_residual(view.image[..., 0].numpy() > 128) < 0.6


def test_point_cloud_from_ply(tmp_path):
    from plyfile import PlyData, PlyElement

    pts = np.zeros(5, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    pts["x"] = np.arange(5)
    pts["red"] = 200
    PlyData([PlyElement.describe(pts, "vertex")]).write(str(tmp_path / "points.ply"))
    write_transforms_scene(tmp_path, ply="points.ply")
    scene = load_scene(tmp_path, load_images_now=False)
    torch.testing.assert_close(scene.points[:, 0], torch.arange(5.0))
    assert (scene.colors[:, 0] == 200).all()


def test_random_points_inside_every_frustum(tmp_path):
    write_transforms_scene(tmp_path)
    scene = load_scene(tmp_path, load_images_now=False)
    assert scene.points.shape == (100_000, 3)
    for view in scene.views:
        cam = scene.points.double() @ view.viewmat[:3, :3].double().T + view.viewmat[:3, 3].double()
        u = view.K[0, 0] * cam[:, 0] / cam[:, 2] + view.K[0, 2]
        v = view.K[1, 1] * cam[:, 1] / cam[:, 2] + view.K[1, 2]
        assert ((cam[:, 2] > 0) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)).all()


def test_missing_frames_refused_or_skipped(tmp_path, caplog):
    write_transforms_scene(tmp_path)
    os.remove(tmp_path / "images" / "frame_004.png")
    with pytest.raises(InputError, match=r"1 of 10 frames have no image file, first \['images/frame_004'\]"):
        load_scene(tmp_path)
    with caplog.at_level(logging.WARNING, logger="cdcgs"):
        scene = load_scene(tmp_path, skip_missing=True, load_images_now=False)
    assert len(scene.views) == 9 and any("skipping" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    "content,match",
    [
        ("{not json", "malformed JSON"),
        ("[]", "non-empty 'frames' list"),
        ('{"frames": []}', "non-empty 'frames' list"),
        ('{"frames": [{"transform_matrix": []}]}', "needs a 'file_path'"),
        ('{"frames": [{"file_path": "images/frame_000"}], "fl_x": 40}', "needs a 'transform_matrix'"),
        (
            '{"frames": [{"file_path": "images/frame_000", "transform_matrix": [[1, 0], [0, 1]]}], "fl_x": 40}',
            "finite 4x4",
        ),
        (
            '{"frames": [{"file_path": "images/frame_000", "transform_matrix": [[2,0,0,0],[0,2,0,0],[0,0,2,0],[0,0,0,1]]}], "fl_x": 40}',
            "not orthonormal",
        ),
        (
            '{"frames": [{"file_path": "images/frame_000", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}',
            "no focal length",
        ),
        (
            '{"frames": [{"file_path": "images/frame_000", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}], "fl_x": "big"}',
            "'fl_x' must be a finite number",
        ),
        (
            '{"frames": [{"file_path": "images/frame_000", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}], "fl_x": 1e20}',
            r"focal length fx = 1e\+20 px is not plausible for an image 40 px across",
        ),
        (
            '{"frames": [{"file_path": "images/frame_000", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}], "fl_x": 40, "w": 99}',
            "image is 40x30 but transforms.json says 99x30",
        ),
        (
            '{"frames": [{"file_path": "images/frame_000", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}], "fl_x": 40, "ply_file_path": "none.ply"}',
            "cannot read the initial point cloud",
        ),
    ],
)
def test_malformed_transforms(tmp_path, content, match):
    write_transforms_scene(tmp_path)
    (tmp_path / "transforms.json").write_text(content)
    with pytest.raises(InputError, match=match) as err:
        load_scene(tmp_path, load_images_now=False)
    assert err.value.path.endswith(("transforms.json", "none.ply", "frame_000.png"))
