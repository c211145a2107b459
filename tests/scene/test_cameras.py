"""COLMAP (text and binary) and transforms.json: round trips, conventions and errors."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from olsplat_nodes.errors import OlsplatInputError, SceneFormatError
from olsplat_nodes.scene import (
    Camera,
    intrinsics,
    look_at,
    read_cameras,
    read_colmap,
    read_transforms_json,
    select_view,
    write_colmap,
    write_transforms_json,
)
from olsplat_nodes.scene.rotations import quat_to_rotmat, rotmat_to_quat


def some_cameras() -> list[Camera]:
    rng = np.random.default_rng(0)
    out = []
    models = [
        ("SIMPLE_PINHOLE", []),
        ("PINHOLE", []),
        ("SIMPLE_RADIAL", [0.03, 0, 0, 0]),
        ("RADIAL", [0.03, -0.01, 0, 0]),
        ("OPENCV", [0.03, -0.01, 0.001, -0.002]),
        ("FULL_OPENCV", [0.03, -0.01, 0.001, -0.002, 0.004, 0.1, 0.02, 0.003]),
    ]
    for i, (model, dist) in enumerate(models):
        f = 500.0 + 10 * i
        fy = f if model.startswith(("SIMPLE", "RADIAL")) else f * 1.01
        pose = look_at(rng.uniform(-50, 50, 3) + np.array([0, 0, 80]), rng.uniform(-5, 5, 3), (0, 0, 1))
        out.append(Camera(f"img_{i:02d}.jpg", 640, 480, intrinsics(f, fy, 320.5, 239.5), pose, dist, model))
    return out


def assert_same_cameras(a: list[Camera], b: list[Camera]):
    assert [c.name for c in a] == [c.name for c in b]
    for x, y in zip(a, b, strict=True):
        assert (x.width, x.height, x.model) == (y.width, y.height, y.model)
        np.testing.assert_allclose(x.K, y.K)
        np.testing.assert_allclose(x.dist, y.dist)
        np.testing.assert_allclose(x.world_from_camera, y.world_from_camera, atol=1e-9)


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_round_trip(tmp_path, binary):
    cameras = some_cameras()
    write_colmap(tmp_path / "sparse" / "0", cameras, binary=binary)
    assert (tmp_path / "sparse" / "0" / ("cameras.bin" if binary else "cameras.txt")).is_file()
    assert_same_cameras(read_colmap(tmp_path), cameras)  # finds sparse/0 by itself


def test_colmap_pose_convention(tmp_path):
    """A hand-written model: identity rotation, t = (0, 0, 5) puts the camera centre at z = -5."""
    (tmp_path / "cameras.txt").write_text("# comment\n1 PINHOLE 100 80 90 91 50 40\n")
    (tmp_path / "images.txt").write_text(
        "1 1 0 0 0 0 0 5 1 a.png\n\n2 0.7071067811865476 0 0.7071067811865476 0 0 0 0 1 b.png\n1 2 -1\n"
    )
    a, b = read_colmap(tmp_path)
    np.testing.assert_allclose(a.center, [0, 0, -5])
    np.testing.assert_allclose(a.K, [[90, 0, 50], [0, 91, 40], [0, 0, 1]])
    # b: camera_from_world rotates +90 degrees about y; its optical axis in the world is -x
    np.testing.assert_allclose(b.world_from_camera[:3, 2], [-1, 0, 0], atol=1e-12)


def test_colmap_shared_intrinsics_are_written_once(tmp_path):
    K = intrinsics(400, 400, 200, 150)
    cameras = [Camera(f"{i}.png", 400, 300, K, look_at([i, 0, 10], [0, 0, 0])) for i in range(5)]
    write_colmap(tmp_path, cameras, binary=False)
    lines = [ln for ln in (tmp_path / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines) == 1


def test_colmap_unsupported_model_text(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 OPENCV_FISHEYE 100 80 90 91 50 40 0 0 0 0\n")
    (tmp_path / "images.txt").write_text("")
    with pytest.raises(SceneFormatError, match=r"cameras.txt: camera 1 uses the unsupported model OPENCV_FISHEYE"):
        read_colmap(tmp_path)


def test_colmap_unsupported_model_binary(tmp_path):
    (tmp_path / "cameras.bin").write_bytes(struct.pack("<QiiQQ8d", 1, 1, 5, 10, 10, *range(8)))
    (tmp_path / "images.bin").write_bytes(struct.pack("<Q", 0))
    with pytest.raises(SceneFormatError, match="unsupported model OPENCV_FISHEYE"):
        read_colmap(tmp_path)


def test_colmap_truncated_binary(tmp_path):
    write_colmap(tmp_path, some_cameras(), binary=True)
    data = (tmp_path / "images.bin").read_bytes()
    (tmp_path / "images.bin").write_bytes(data[:-30])
    with pytest.raises(SceneFormatError, match=r"images.bin: file is truncated"):
        read_colmap(tmp_path)


def test_colmap_missing_camera_and_bad_lines(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 100 80 90 91 50 40\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 5 7 a.png\n\n")
    with pytest.raises(SceneFormatError, match="refers to camera 7"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 100 80 90 91\n")
    with pytest.raises(SceneFormatError, match="PINHOLE needs 4 parameters, got 2"):
        read_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE abc 80 90 91 50 40\n")
    with pytest.raises(SceneFormatError, match="malformed camera line"):
        read_colmap(tmp_path)


def test_no_model_here(tmp_path):
    with pytest.raises(SceneFormatError, match="no COLMAP model here"):
        read_cameras(tmp_path)


def test_transforms_round_trip(tmp_path):
    cameras = [c for c in some_cameras() if c.model in ("PINHOLE", "OPENCV")]
    write_transforms_json(tmp_path / "transforms.json", cameras)
    back = read_cameras(tmp_path / "transforms.json")
    assert_same_cameras(back, cameras)
    assert_same_cameras(read_cameras(tmp_path), cameras)  # a folder holding transforms.json


def test_transforms_opengl_convention_and_camera_angle(tmp_path):
    """instant-ngp style: camera_angle_x only; an identity GL pose looks down world -z."""
    meta = {
        "camera_angle_x": 2 * np.arctan(0.5),
        "w": 200,
        "h": 100,
        "frames": [{"file_path": "./a", "transform_matrix": np.eye(4).tolist()}],
    }
    (tmp_path / "t.json").write_text(json.dumps(meta))
    (camera,) = read_transforms_json(tmp_path / "t.json")
    assert camera.fx == pytest.approx(200.0) and camera.fy == pytest.approx(200.0)
    assert (camera.cx, camera.cy) == (100.0, 50.0)
    np.testing.assert_allclose(camera.world_from_camera[:3, 2], [0, 0, -1])  # optical axis
    np.testing.assert_allclose(camera.world_from_camera[:3, 1], [0, -1, 0])  # image down


def test_transforms_size_from_the_image(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "frame.png"), np.zeros((30, 40, 3), np.uint8))
    meta = {"fl_x": 50, "frames": [{"file_path": "frame.png", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    (camera,) = read_transforms_json(tmp_path / "transforms.json")
    assert (camera.width, camera.height, camera.fy) == (40, 30, 50.0)


@pytest.mark.parametrize(
    "meta,message",
    [
        ({"w": 10, "h": 10, "frames": [{"file_path": "a", "transform_matrix": np.eye(4).tolist()}]}, "no intrinsics"),
        ({"fl_x": 5, "frames": [{"file_path": "a", "transform_matrix": np.eye(4).tolist()}]}, "no image size"),
        ({"fl_x": 5, "w": 10, "h": 10, "frames": []}, "no 'frames' list"),
        ({"fl_x": 5, "w": 10, "h": 10, "frames": [{"file_path": "a"}]}, "lacks 'file_path' or 'transform_matrix'"),
        ({"camera_model": "OPENCV_FISHEYE", "fl_x": 5, "w": 9, "h": 9, "frames": [{}]}, "unsupported camera_model"),
        (
            {"fl_x": 5, "w": 10, "h": 10, "frames": [{"file_path": "a", "transform_matrix": [[2, 0, 0, 0]] * 4}]},
            "not a rigid",
        ),
    ],
)
def test_transforms_errors(tmp_path, meta, message):
    (tmp_path / "t.json").write_text(json.dumps(meta))
    with pytest.raises(SceneFormatError, match=message):
        read_transforms_json(tmp_path / "t.json")


def test_transforms_not_json(tmp_path):
    (tmp_path / "t.json").write_text("{oops")
    with pytest.raises(SceneFormatError, match=r"t\.json: not valid JSON"):
        read_transforms_json(tmp_path / "t.json")


def test_select_view():
    cameras = some_cameras()
    assert select_view(cameras, "img_02.jpg") is cameras[2]
    assert select_view(cameras, "img_03") is cameras[3]
    assert select_view(cameras, "4") is cameras[4]
    assert select_view(cameras, -1) is cameras[-1]
    with pytest.raises(OlsplatInputError, match=r"no view 'missing'.*index in 0..5"):
        select_view(cameras, "missing")
    with pytest.raises(OlsplatInputError, match="no view '17'"):
        select_view(cameras, 17)


def test_quaternion_round_trip():
    rng = np.random.default_rng(1)
    for q in rng.normal(size=(200, 4)):
        q /= np.linalg.norm(q)
        q *= np.sign(q[0])
        np.testing.assert_allclose(rotmat_to_quat(quat_to_rotmat(q)), q, atol=1e-9)


def test_camera_rejects_bad_values():
    with pytest.raises(ValueError, match="image size must be positive"):
        Camera("c", 0, 10, np.eye(3), np.eye(4))
    with pytest.raises(ValueError, match="focal lengths"):
        Camera("c", 10, 10, np.zeros((3, 3)), np.eye(4))


def test_a_scaled_camera_maps_pixel_edges_onto_the_smaller_image():
    """Camera.scaled: a world point's pixel coordinates (top-left pixel centre at 0.5) scale by
    the ratio of the sizes, so the image's edges stay its edges; the pose does not change."""
    camera = Camera("v", 320, 240, intrinsics(300.0, 290.0, 161.0, 119.5), look_at([0, -20, 10], [0, 0, 0]))
    small = camera.scaled(0.5)
    assert (small.width, small.height, small.name) == (160, 120, "v")
    np.testing.assert_array_equal(small.world_from_camera, camera.world_from_camera)
    rng = np.random.default_rng(0)
    points = rng.normal(size=(20, 3)) * 3.0
    for cam, scale in ((camera, 1.0), (small, 0.5)):
        local = (cam.camera_from_world[:3, :3] @ points.T).T + cam.camera_from_world[:3, 3]
        uv = (cam.K @ local.T).T
        uv = uv[:, :2] / uv[:, 2:]
        if scale == 1.0:
            full = uv
        else:
            np.testing.assert_allclose(uv, full * 0.5, rtol=1e-12, atol=1e-9)
    odd = camera.scaled(1 / 3)  # 106.67 x 80 -> 107 x 80: each axis by its own exact ratio
    assert (odd.width, odd.height) == (107, 80)
    np.testing.assert_allclose(odd.K[0], camera.K[0] * 107 / 320)
    np.testing.assert_allclose(odd.K[1], camera.K[1] * 80 / 240)
