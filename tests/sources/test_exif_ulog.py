"""The exif_folder source with a PX4 flight log beside the photos: JPEGs with EXIF GPS written here,
and a ULog of the analytic flight in tests/telemetry/ulog_files.py."""

from __future__ import annotations

import datetime as dt
import logging

import numpy as np
import pytest

from olsplat_nodes.errors import OlsplatInputError, SceneFormatError
from olsplat_nodes.sources import ExifFolderSource, open_source
from olsplat_nodes.telemetry import CameraMount, euler_to_rotmat, geodetic_to_ned, world_from_camera

from ..telemetry.ulog_files import TRIGGERS_S, UTC_BOOT_US, flight_topics, geodetic, stamps_us, truth, write_ulog
from .conftest import write_photo

CAMERA_CLOCK_S = 4 * 3600 + 17  # the camera's clock runs 4 h 17 s ahead of UTC (1 s resolution)


def photo_time(t_s: float) -> str:
    utc = (UTC_BOOT_US + int(stamps_us(t_s))) / 1e6 + CAMERA_CLOCK_S
    return dt.datetime.fromtimestamp(int(utc), dt.UTC).strftime("%Y:%m:%d %H:%M:%S")


def write_flight(folder, photos_at=TRIGGERS_S, *, gps_noise_m=(2.0, -1.5, 3.0)):
    """One JPEG per time in ``photos_at`` (EXIF GPS = the truth + ``gps_noise_m`` NED) and the log."""
    folder.mkdir(exist_ok=True)
    for i, t in enumerate(photos_at):
        lat, lon, alt = geodetic(truth(t)[0] + np.asarray(gps_noise_m))
        write_photo(folder / f"P{i:03d}.jpg", lat, lon, alt, photo_time(t), offset="+00:00", seed=i)
    return write_ulog(folder / "flight.ulg", flight_topics())


def expected_pose(t_s: float, reference, mount: CameraMount) -> np.ndarray:
    ned, roll, pitch, yaw = truth(t_s)
    return world_from_camera(geodetic_to_ned(*geodetic(ned), reference), euler_to_rotmat(roll, pitch, yaw), mount)


def assert_pose(got, want):
    cos = (np.trace(got[:3, :3].T @ want[:3, :3]) - 1.0) / 2.0
    assert np.arccos(np.clip(cos, -1.0, 1.0)) < 1e-3
    np.testing.assert_allclose(got[:3, 3], want[:3, 3], atol=1e-3)


def test_the_log_beside_the_photos_gives_their_attitude_and_position(tmp_path, caplog):
    write_flight(tmp_path / "photos")
    with caplog.at_level(logging.INFO, logger="olsplat_nodes"):
        source = open_source({"source_kind": "exif_folder", "source": str(tmp_path / "photos"), "fast": True})
    frames = list(source)
    assert source.heading_sources == ["vehicle_attitude"] * 6 and source.ulog.match.method == "order"
    assert source.stats["ulog_matched"] == 6 and not [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("6 of 6 photos matched to 6 camera_capture triggers in order" in r.getMessage() for r in caplog.records)
    for frame, t in zip(frames, TRIGGERS_S, strict=True):
        assert_pose(frame.camera.world_from_camera, expected_pose(t, source.reference, CameraMount()))
    # the EXIF-only prior would look along the travel (45 degrees) from the noisy GPS fix
    plain = ExifFolderSource(tmp_path / "photos", ulog="none")
    assert plain.heading_sources == ["travel"] * 6
    assert np.linalg.norm(plain.poses[0, :3, 3] - frames[0].camera.world_from_camera[:3, 3]) > 3.0


def test_a_dropped_photo_and_a_stray_one_are_matched_by_time(tmp_path, caplog):
    times = [t for i, t in enumerate(TRIGGERS_S) if i != 2] + [TRIGGERS_S[-1] + 5.0]  # the stray: no trigger
    write_flight(tmp_path, times)
    with caplog.at_level(logging.WARNING):
        source = ExifFolderSource(tmp_path, mount_rpy_deg=(0.0, -60.0, 10.0))
    match = source.ulog.match
    assert match.method == "time" and match.capture_of_photo.tolist() == [0, 1, 3, 4, 5, -1]
    assert match.offset_s == pytest.approx(CAMERA_CLOCK_S - 0.4, abs=0.1)  # the triggers' fractions of a second
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'flight.ulg'}: 1 of 6 photos keep their EXIF-only prior: 1 without a trigger"
    ]
    mount = CameraMount.from_angles(0.0, -60.0, 10.0)
    for pose, t in zip(source.poses[:5], times, strict=False):
        assert_pose(pose, expected_pose(t, source.reference, mount))
    assert source.heading_sources[5] == "travel"
    np.testing.assert_array_equal(source.poses[5], ExifFolderSource(tmp_path, ulog="none").poses[5])


def test_a_photo_without_gps_takes_the_log_position(tmp_path):
    from PIL import Image

    write_flight(tmp_path)
    with Image.open(tmp_path / "P003.jpg") as image:
        image.load()
        exif = image.getexif()
    del exif[0x8825]  # the GPS IFD
    image.save(tmp_path / "P003.jpg", "JPEG", quality=90, exif=exif)
    source = ExifFolderSource(tmp_path)
    assert len(source.photos) == 6 and source.stats["photos_without_gps"] == 0
    assert_pose(source.poses[3], expected_pose(TRIGGERS_S[3], source.reference, CameraMount()))
    assert len(ExifFolderSource(tmp_path, ulog="none").photos) == 5


def test_which_log_and_bad_logs(tmp_path, caplog):
    write_flight(tmp_path / "photos")
    (tmp_path / "photos" / "flight.ulg").rename(tmp_path / "elsewhere.ulg")
    assert ExifFolderSource(tmp_path / "photos").ulog is None  # no .ulg in the folder: EXIF only
    source = open_source(
        {"source_kind": "exif_folder", "source": str(tmp_path / "photos"), "exif_ulog": str(tmp_path / "elsewhere.ulg")}
    )
    assert source.heading_sources == ["vehicle_attitude"] * 6
    with pytest.raises(OlsplatInputError, match=r"exif_ulog='.*nope\.ulg' is not a file"):
        ExifFolderSource(tmp_path / "photos", ulog=str(tmp_path / "nope.ulg"))
    (tmp_path / "photos" / "a.ulg").write_bytes(b"")
    (tmp_path / "photos" / "b.ulg").write_bytes(b"")
    with caplog.at_level(logging.WARNING):
        assert ExifFolderSource(tmp_path / "photos").ulog is None
    assert [r.getMessage() for r in caplog.records] == [
        f"exif_folder {tmp_path / 'photos'}: 2 .ulg files (a.ulg, b.ulg): none used; set exif_ulog to one of them"
    ]
    (tmp_path / "photos" / "b.ulg").unlink()
    with pytest.raises(SceneFormatError, match=r"photos/a\.ulg: not a readable ULog file"):
        ExifFolderSource(tmp_path / "photos")
    assert ExifFolderSource(tmp_path / "photos", ulog="none").ulog is None
