"""scene/geodesy.py: our ``geodetic_to_ned`` against pymap3d's (a maintained library), ENU <->
geodetic round trips, the EPSG path against pyproj's UTM, and georef.json read/write/refusals."""

from __future__ import annotations

import json

import numpy as np
import pymap3d
import pytest

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.scene.geodesy import (
    Georeference,
    enu_to_geodetic,
    find_georef,
    geodetic_to_enu,
    geodetic_to_ned,
    read_georef,
    write_georef,
)
from olsplat_nodes.telemetry import geodetic_to_ned as telemetry_geodetic_to_ned

ORIGINS = [(47.3769, 8.5417, 408.0), (-33.86, 151.21, 20.0), (64.1, -21.9, -30.0), (0.0, 179.9, 0.0)]


@pytest.mark.parametrize("origin", ORIGINS)
def test_our_geodetic_to_ned_matches_pymap3d_to_a_millimetre(origin):
    rng = np.random.default_rng(0)
    lat = origin[0] + rng.uniform(-0.02, 0.02, 200)  # ~2 km around the origin
    lon = origin[1] + rng.uniform(-0.02, 0.02, 200)
    alt = origin[2] + rng.uniform(-50.0, 300.0, 200)
    ours = geodetic_to_ned(lat, lon, alt, origin)
    n, e, d = pymap3d.geodetic2ned(lat, lon, alt, *origin)
    theirs = np.stack([n, e, d], -1)
    assert np.abs(ours - theirs).max() < 1e-3  # metres
    assert np.abs(ours).max() > 1000  # not trivially zero
    assert telemetry_geodetic_to_ned is geodetic_to_ned  # the telemetry's old name is this function


@pytest.mark.parametrize("origin", ORIGINS)
def test_enu_geodetic_round_trip(origin):
    points = np.array([[0.0, 0.0, 0.0], [100.0, 200.0, 10.0], [-350.0, 80.0, -20.0], [1500.0, -900.0, 120.0]])
    lat, lon, alt = enu_to_geodetic(points, origin)
    assert (lat[0], lon[0], alt[0]) == pytest.approx(origin, abs=1e-9)
    np.testing.assert_allclose(geodetic_to_enu(lat, lon, alt, origin), points, atol=1e-6)
    # and through our own NED: the same point (ENU = NED with x, y swapped and z negated)
    ned = geodetic_to_ned(lat, lon, alt, origin)
    np.testing.assert_allclose(ned[:, [1, 0]], points[:, :2], atol=1e-3)
    np.testing.assert_allclose(-ned[:, 2], points[:, 2], atol=1e-3)


def test_north_is_north_and_east_is_east():
    lat, lon, alt = Georeference(47.0, 8.0, 400.0).to_geodetic([[0.0, 1000.0, 0.0], [1000.0, 0.0, 0.0]])
    assert lat[0] > 47.0 and lon[0] == pytest.approx(8.0, abs=1e-12)  # +y: north
    assert lon[1] > 8.0 and lat[1] == pytest.approx(47.0, abs=1e-4)  # +x: east
    assert lat[0] - 47.0 == pytest.approx(1000.0 / 111_200, rel=0.01)  # a degree of latitude ~111.2 km
    assert alt[0] == pytest.approx(400.0 + 1000.0**2 / (2 * 6.37e6), abs=0.01)  # the Earth curves away


def test_epsg_georeference_through_a_rotated_map():
    """A map whose world is UTM zone 32N turned by 30 degrees and shifted (crs_from_map): known
    WGS-84 points, put into the map's frame through pyproj's forward projection, come back."""
    pytest.importorskip("pyproj")
    from pyproj import Transformer

    lat = np.array([47.3769, 47.3775, 47.3760])
    lon = np.array([8.5417, 8.5430, 8.5401])
    east, north = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True).transform(lon, lat)
    turn = np.radians(30.0)
    crs_from_map = np.eye(4)
    crs_from_map[:2, :2] = [[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]
    crs_from_map[:3, 3] = [east[0], north[0], 408.0]
    crs = np.stack([east, north, [410.0, 420.0, 400.0]], -1)
    points = (crs - crs_from_map[:3, 3]) @ crs_from_map[:3, :3]  # map frame: R^T (crs - t)
    got_lat, got_lon, got_alt = Georeference(axes="epsg", epsg=32632, crs_from_map=crs_from_map).to_geodetic(points)
    np.testing.assert_allclose(got_lat, lat, atol=1e-9)
    np.testing.assert_allclose(got_lon, lon, atol=1e-9)
    np.testing.assert_allclose(got_alt, [410.0, 420.0, 400.0], atol=1e-9)
    assert np.abs(points[1:, :2]).max() > 50  # the map's own coordinates, not the CRS's


def test_georef_json_round_trip_and_find(tmp_path):
    georef = Georeference(47.0, 8.0, 400.0, height_ref="msl", source="a test")
    path = write_georef(tmp_path, georef)
    assert path == tmp_path / "georef.json" and find_georef(tmp_path / "none", tmp_path) == path
    assert json.loads(path.read_text())["axes"] == "enu"
    assert read_georef(path) == georef
    epsg = Georeference(axes="epsg", epsg=32632, crs_from_map=np.eye(4), altitude=0.0)
    again = read_georef(write_georef(tmp_path / "utm.json", epsg))
    assert again.epsg == 32632 and np.array_equal(again.crs_from_map, np.eye(4))
    assert find_georef(tmp_path / "none") is None


@pytest.mark.parametrize(
    ("doc", "words"),
    [
        ("[1, 2]", "expected a JSON object"),
        ('{"version": 2}', "version: 2"),
        ('{"version": 1, "latitude": 47.0, "longitude": 8.0}', "altitude: missing"),
        ('{"version": 1, "latitude": "47", "longitude": 8.0, "altitude": 1}', "latitude: '47' is not a number"),
        ('{"version": 1, "latitude": 97.0, "longitude": 8.0, "altitude": 1}', "latitude: 97.0 is not in -90..90"),
        ('{"version": 1, "latitude": 7.0, "longitude": 8.0, "altitude": 1, "height_ref": "geoid"}', "height_ref"),
        ('{"version": 1, "axes": "epsg", "epsg": 32632, "crs_from_map": [[1, 0]]}', "crs_from_map: expected 4 rows"),
        ('{"version": 1, "axes": "ned", "latitude": 1, "longitude": 1, "altitude": 1}', "axes: 'ned'"),
        ("{not json", "not JSON"),
    ],
)
def test_bad_georef_files_are_refused_in_one_line_naming_file_and_field(tmp_path, doc, words):
    path = tmp_path / "georef.json"
    path.write_text(doc)
    with pytest.raises(SceneFormatError) as caught:
        read_georef(path)
    message = str(caught.value)
    assert message.startswith(str(path)) and words in message and "\n" not in message
