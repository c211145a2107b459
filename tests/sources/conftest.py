"""Small geotagged JPEGs written with Pillow (EXIF GPS, times, focal lengths, optional DJI XMP)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


def _dms(value: float) -> tuple[float, float, float]:
    value = abs(value)
    d = int(value)
    m = int((value - d) * 60)
    return (float(d), float(m), round((value - d - m / 60) * 3600, 4))


def write_photo(
    path: Path,
    lat: float,
    lon: float,
    alt: float,
    when: str,
    *,
    size=(160, 120),
    f35: float | None = 24.0,
    focal_mm: float | None = None,
    plane_res: tuple[float, int, int] | None = None,
    offset: str | None = None,
    gps_utc: tuple[str, tuple[float, float, float]] | None = None,
    xmp: str | None = None,
    seed: int = 0,
) -> Path:
    """A JPEG with EXIF: GPS (lat/lon degrees, alt m AMSL), DateTimeOriginal ``when``, focal data, optional XMP."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    pixels = rng.integers(0, 256, (size[1] // 8, size[0] // 8, 3), dtype=np.uint8).repeat(8, 0).repeat(8, 1)
    image = Image.fromarray(pixels)
    exif = Image.Exif()
    exif[0x0110] = "TestCam"
    gps = {
        1: "N" if lat >= 0 else "S",
        2: _dms(lat),
        3: "E" if lon >= 0 else "W",
        4: _dms(lon),
        5: b"\x00",
        6: float(alt),
    }
    if gps_utc:
        gps[29], gps[7] = gps_utc
    exif[0x8825] = gps
    ifd = {0x9003: when}
    if f35:
        ifd[0xA405] = int(f35)
    if focal_mm:
        ifd[0x920A] = float(focal_mm)
    if plane_res:
        ifd[0xA20E], ifd[0xA210], ifd[0xA002] = float(plane_res[0]), plane_res[1], plane_res[2]
    if offset:
        ifd[0x9011] = offset
    exif[0x8769] = ifd
    kwargs = {"xmp": xmp.encode()} if xmp else {}
    image.save(path, "JPEG", quality=90, exif=exif, **kwargs)
    return path


def dji_xmp(gimbal_yaw: float, gimbal_pitch: float = -90.0, flight_yaw: float = 0.0) -> str:
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
        '<rdf:Description rdf:about="" xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
        f'drone-dji:GimbalYawDegree="{gimbal_yaw:+.2f}" drone-dji:GimbalPitchDegree="{gimbal_pitch:+.2f}" '
        f'drone-dji:GimbalRollDegree="+0.00" drone-dji:FlightYawDegree="{flight_yaw:+.2f}"/></rdf:RDF></x:xmpmeta>'
    )


# A short flight: east, east, then north (about 11 m per step at 30 degrees north).
TRACK = [(30.0, -98.0, 400.0), (30.0, -97.99989, 401.0), (30.0, -97.99978, 402.0), (30.0001, -97.99978, 402.0)]


@pytest.fixture
def photo_folder(tmp_path) -> Path:
    folder = tmp_path / "photos"
    folder.mkdir()
    for i, (lat, lon, alt) in enumerate(TRACK):
        write_photo(
            folder / f"IMG_{i:04d}.jpg", lat, lon, alt, f"2024:05:01 10:00:{2 * i:02d}", offset="+02:00", seed=i
        )
    return folder
