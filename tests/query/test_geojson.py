"""query/geojson.py: 3D instances located through a georeference and written as GeoJSON (checked
by the geojson package: valid, [lon, lat, alt] order, closed counter-clockwise rings, 8
decimals) and KML (read back by the standard library's XML parser); the wire records of a
reply give the same places."""

from __future__ import annotations

import itertools
import json
import math
from types import SimpleNamespace
from xml.etree import ElementTree

import geojson
import numpy as np
import pymap3d
import pytest

from olsplat_msgs import QueryRequest, decode, encode
from olsplat_nodes.query.geojson import (
    dumps_geojson,
    feature_collection,
    from_records,
    kml_document,
    locate,
)
from olsplat_nodes.query.localize import Instance3D
from olsplat_nodes.scene.geodesy import Georeference
from olsplat_nodes.transport.convert import reply_for

GEOREF = Georeference(47.397742, 8.545594, 488.0)
INSTANCES = [
    Instance3D((10.0, -5.5, 0.25), (15.0, -1.0, 5.5), (12.5, -3.25, 4.0), 412),
    Instance3D((-40.0, 20.0, 0.0), (-30.0, 31.0, 7.0), (-35.0, 25.5, 3.5), 120),
]


def _signed_area(ring) -> float:
    return 0.5 * sum(a[0] * b[1] - b[0] * a[1] for a, b in itertools.pairwise(ring))


def test_locate_puts_the_centre_and_corners_where_pymap3d_does():
    located = locate(INSTANCES, GEOREF)
    for inst, place in zip(INSTANCES, located, strict=True):
        lat, lon, alt = pymap3d.enu2geodetic(*inst.centre, *GEOREF.origin)
        assert (place.latitude, place.longitude, place.altitude) == pytest.approx((lat, lon, alt), abs=1e-9)
        (x0, y0, z0), (x1, y1, z1) = inst.box_min, inst.box_max
        for (x, y), (lon_c, lat_c) in zip([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], place.footprint, strict=True):
            want_lat, want_lon, _ = pymap3d.enu2geodetic(x, y, z0, *GEOREF.origin)
            assert (lat_c, lon_c) == pytest.approx((want_lat, want_lon), abs=1e-9)
        assert place.box_altitude == pytest.approx((488.0 + z0, 488.0 + z1), abs=0.01)
        assert place.extent == pytest.approx((x1 - x0, y1 - y0, z1 - z0))
    assert [p.rank for p in located] == [0, 1]
    unplaced = locate(INSTANCES, None)
    assert not any(p.located for p in unplaced) and math.isnan(unplaced[0].altitude)


def test_geojson_is_valid_lon_lat_ordered_closed_ccw_and_8_decimals():
    text = dumps_geojson(feature_collection(locate(INSTANCES, GEOREF), "red roof buildings", 7, "ellipsoid"))
    collection = geojson.loads(text)
    assert collection.is_valid and collection["type"] == "FeatureCollection"
    assert len(collection["features"]) == len(INSTANCES)
    for feature, inst in zip(collection["features"], INSTANCES, strict=True):
        assert feature.is_valid
        polygon = feature["geometry"]
        assert polygon["type"] == "Polygon"
        lon, lat, alt = feature["properties"]["centre"]
        assert 8.5 < lon < 8.6 and 47.3 < lat < 47.4 and 480 < alt < 500  # longitude first
        ring = polygon["coordinates"][0]
        assert len(ring) == 5 and ring[0] == ring[-1]  # closed
        assert [corner[2] for corner in ring] == pytest.approx(
            [feature["properties"]["altitude_min"]] * 5, abs=1e-3
        )  # at the box's bottom
        assert min(c[0] for c in ring) < lon < max(c[0] for c in ring) and min(c[1] for c in ring) < lat < max(
            c[1] for c in ring
        )
        assert _signed_area(ring) > 0  # counter-clockwise: RFC 7946's exterior ring
        props = feature["properties"]
        assert props["query"] == "red roof buildings" and props["map_version"] == 7
        assert props["gaussians"] == inst.gaussians and props["height_ref"] == "ellipsoid"
        assert props["score"] == pytest.approx(inst.gaussians / 532, abs=1e-6)
        assert props["extent_m"] == pytest.approx(np.subtract(inst.box_max, inst.box_min).tolist(), abs=1e-3)
        assert props["altitude_min"] <= props["altitude"] <= props["altitude_max"]
    # 8 decimals, not the package's default 6 (~0.1 m)
    numbers = [c for corner in json.loads(text)["features"][0]["geometry"]["coordinates"][0] for c in corner[:2]]
    assert all(len(repr(c).split(".")[1]) <= 8 for c in numbers)
    assert any(len(repr(c).split(".")[1]) > 6 for c in numbers)


def test_without_a_georeference_nothing_is_written():
    with pytest.raises(ValueError, match="no georeference"):
        feature_collection(locate(INSTANCES, None), "roof", 1, "")
    with pytest.raises(ValueError, match="no georeference"):
        kml_document(locate(INSTANCES, None), "roof", 1, "")


def test_kml_reads_back_with_the_footprint_and_properties():
    text = kml_document(locate(INSTANCES, GEOREF), "red roof buildings", 3, "ellipsoid")
    root = ElementTree.fromstring(text.encode())
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    marks = root.findall("k:Document/k:Placemark", ns)
    assert len(marks) == 2
    ring = marks[0].find("k:MultiGeometry/k:Polygon/k:outerBoundaryIs/k:LinearRing/k:coordinates", ns).text
    corners = [tuple(float(v) for v in pair.split(",")) for pair in ring.split()]
    assert corners[0] == corners[-1] and len(corners) == 5 and _signed_area(corners) > 0
    assert corners[0] == pytest.approx(locate(INSTANCES, GEOREF)[0].footprint[0], abs=1e-8)
    data = {d.get("name"): d.find("k:value", ns).text for d in marks[0].findall("k:ExtendedData/k:Data", ns)}
    assert data["query"] == "red roof buildings" and data["gaussians"] == "412" and data["map_version"] == "3"


def test_the_wire_records_give_the_same_places():
    """reply_for's records, encoded and decoded as a ground station receives them, locate the
    instances as the core does; without a georeference they carry NaN and an empty height_ref."""
    answer = SimpleNamespace(
        instances=INSTANCES, regions=[], chosen_count=600, negatives=["road"], unknown_words=[], text="roof"
    )
    answer.heatmap = answer.mask = None
    for georef in (GEOREF, None):
        reply = reply_for(answer, QueryRequest(request_id="r", text="roof"), 4, None, 0.0, georef)
        _, received = decode(encode(reply, "query"))
        assert received.height_ref == ("ellipsoid" if georef else "")
        got, want = from_records(received.instances), locate(INSTANCES, georef)
        if georef is None:
            assert all(math.isnan(r["latitude"]) and math.isnan(r["footprint"][0]) for r in received.instances)
            continue
        assert got == want
