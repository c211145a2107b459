"""The exif_folder source on JPEGs written here, and on the shared real UAV photos when present."""

from __future__ import annotations

import datetime as dt
import math
from itertools import pairwise

import cv2
import numpy as np
import pytest

from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.sources import ExifFolderSource, focal_length_px, headings_from_track, open_source, read_exif
from olsplat_nodes.telemetry import geodetic_to_ned
from olsplat_nodes.telemetry.pose import ENU_FROM_NED

from ..promised import skip_unless_ci
from .conftest import TRACK, dji_xmp, write_photo


def project(camera, point_world) -> np.ndarray:
    camera_from_world = np.linalg.inv(camera.world_from_camera)
    p = camera_from_world[:3, :3] @ point_world + camera_from_world[:3, 3]
    assert p[2] > 0, "the point is behind the camera"
    return (camera.K @ (p / p[2]))[:2]


def test_exif_is_read_back_as_written(photo_folder):
    photo = read_exif(photo_folder / "IMG_0001.jpg")
    assert photo.lat == pytest.approx(TRACK[1][0], abs=1e-7) and photo.lon == pytest.approx(TRACK[1][1], abs=1e-7)
    assert photo.alt == pytest.approx(401.0) and (photo.width, photo.height) == (160, 120)
    expected = dt.datetime(2024, 5, 1, 10, 0, 2, tzinfo=dt.timezone(dt.timedelta(hours=2)))
    assert photo.stamp_ns == int(expected.timestamp()) * 10**9 and photo.stamp_source == "offset"
    f, rule = focal_length_px(photo)
    assert rule == "FocalLengthIn35mmFilm" and f == pytest.approx(24.0 * math.hypot(160, 120) / math.hypot(36, 24))


def test_positions_are_enu_around_the_first_photo_and_headings_follow_travel(photo_folder):
    source = ExifFolderSource(photo_folder, fast=True)
    frames = list(source)
    assert [f.name for f in frames] == [f"IMG_{i:04d}.jpg" for i in range(4)] and source.done
    ned = geodetic_to_ned(*np.array(TRACK).T, TRACK[0])
    positions = np.array([f.camera.world_from_camera[:3, 3] for f in frames])
    np.testing.assert_allclose(positions, ned @ ENU_FROM_NED.T, atol=1e-6)
    assert positions[1, 0] > 10 and positions[3, 1] > 10  # east, then north
    assert source.heading_sources == ["travel"] * 4
    # nadir, image top towards the direction of travel: a ground point ahead projects above the centre
    for frame, ahead in zip(frames, ([1, 0], [1, 0], [0, 1], [0, 1]), strict=True):
        camera = frame.camera
        ground = camera.world_from_camera[:3, 3] + np.array([*np.multiply(ahead, 5.0), -50.0])
        u, v = project(camera, ground)
        assert v < camera.cy - 5 and abs(u - camera.cx) < 1e-3
        np.testing.assert_allclose(camera.world_from_camera[:3, 2], [0, 0, -1], atol=1e-12)  # optical axis down
    # the original file bytes travel with the frame and decode to the same image
    assert all(
        np.array_equal(cv2.imdecode(np.frombuffer(f.jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1], f.image)
        for f in frames
    )


def test_dji_gimbal_yaw_wins_over_travel(tmp_path):
    for i, (lat, lon, alt) in enumerate(TRACK[:2]):
        write_photo(
            tmp_path / f"DJI_{i}.jpg",
            lat,
            lon,
            alt,
            f"2024:05:01 10:00:0{i}",
            xmp=dji_xmp(gimbal_yaw=90.0),
            f35=None,
            focal_mm=4.5,
            plane_res=(16393.44, 2, 640),
        )
    source = ExifFolderSource(tmp_path, fast=True)
    assert source.heading_sources == ["gimbal_yaw", "gimbal_yaw"] and source.photos[0].gimbal_pitch == -90.0
    camera = source.cameras[0]
    assert source.focal_rules[0] == "FocalLength+FocalPlaneXResolution"
    assert camera.fx == pytest.approx(4.5 * 16393.44 / 25.4 * 160 / 640)  # scaled from the EXIF width to the stored one
    _, v = project(camera, camera.world_from_camera[:3, 3] + [5.0, 0.0, -50.0])  # east is up in the image
    assert v < camera.cy - 5


def test_headings_from_track_skip_hovering():
    positions = np.array([[0, 0, 0], [10, 0, 0], [10.1, 0, 0], [10.1, 10, 0]], float)
    np.testing.assert_allclose(headings_from_track(positions), [90, 90, 0, 0])  # the hover step takes a neighbour's
    np.testing.assert_allclose(headings_from_track(np.zeros((3, 3))), 0)


def test_stamp_zone_from_gps_time_and_errors(tmp_path):
    path = write_photo(
        tmp_path / "a.jpg", 30, -98, 300, "2014:10:19 13:20:51", gps_utc=("2014:10:19", (18.0, 20.0, 52.0))
    )
    photo = read_exif(path)
    assert photo.stamp_source == "gps_zone"
    assert photo.stamp_ns == int(dt.datetime(2014, 10, 19, 18, 20, 51, tzinfo=dt.UTC).timestamp()) * 10**9
    write_photo(tmp_path / "b.jpg", 30, -98, 300, "2014:10:19 13:20:53", f35=None)  # no focal information
    with pytest.raises(OlsplatInputError, match="exif_focal_px"):
        ExifFolderSource(tmp_path)
    assert ExifFolderSource(tmp_path, focal_px=100.0).cameras[1].fx == 100.0
    (tmp_path / "empty").mkdir()
    with pytest.raises(OlsplatInputError, match="no JPEG with EXIF GPS"):
        ExifFolderSource(tmp_path / "empty")
    with pytest.raises(OlsplatInputError, match="not a folder"):
        open_source({"source_kind": "exif_folder", "source": str(tmp_path / "nope")})


def test_caliterra_photos(shared_data):
    folder = shared_data / "caliterra"
    if not folder.is_dir():
        skip_unless_ci("shared data", f"{folder} is absent")
    source = open_source({"source_kind": "exif_folder", "source": str(folder), "fast": True})
    assert len(source.photos) == 24 and source.stats["photos_without_gps"] == 0
    # Canon SX260 HS at 4.5 mm: FocalPlaneXResolution gives ~2904 px at 4000 px wide, 726 px at the 1000 px copy
    assert source.focal_rules[0] == "FocalLength+FocalPlaneXResolution"
    assert source.cameras[0].fx == pytest.approx(726.09, abs=0.1) and (
        source.cameras[0].width,
        source.cameras[0].height,
    ) == (1000, 750)
    stamps = np.array([p.stamp_ns for p in source.photos])
    assert (np.diff(stamps) > 0).all() and {p.stamp_source for p in source.photos} == {"gps_zone"}
    assert dt.datetime.fromtimestamp(stamps[0] / 1e9, dt.UTC) == dt.datetime(2014, 10, 19, 18, 20, 51, tzinfo=dt.UTC)
    positions = np.array([c.world_from_camera[:3, 3] for c in source.cameras])
    steps = np.linalg.norm(np.diff(positions[:, :2], axis=0), axis=1)
    assert np.median(steps) > 3 and steps.max() < 30  # a few metres to ~20 m between photos taken 2 s apart
    # the predicted direction of image motion between consecutive photos (from GPS and the travel
    # heading; independent of the unknown height) agrees with the measured one wherever phase
    # correlation is confident (photos with little rotation between them)
    agree = confident = 0
    frames = list(source)
    for a, b in pairwise(frames):
        move = b.camera.world_from_camera[:3, 3] - a.camera.world_from_camera[:3, 3]
        if np.linalg.norm(move[:2]) < 3:
            continue
        in_camera = a.camera.world_from_camera[:3, :3].T @ np.array([move[0], move[1], 0.0])
        predicted = -in_camera[:2]  # the ground moves opposite to the camera in the image
        gray = [cv2.cvtColor(f.image, cv2.COLOR_RGB2GRAY).astype(np.float32) for f in (a, b)]
        (dx, dy), response = cv2.phaseCorrelate(
            gray[0], gray[1], cv2.createHanningWindow(gray[0].shape[::-1], cv2.CV_32F)
        )
        if response < 0.1:
            continue
        confident += 1
        cos = (predicted @ [dx, dy]) / (np.linalg.norm(predicted) * math.hypot(dx, dy) + 1e-9)
        agree += cos > 0.7
    assert confident >= 5 and agree == confident
