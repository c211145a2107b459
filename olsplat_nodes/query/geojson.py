"""A query's 3D instances on the Earth: located through the map's georeference, and written as
GeoJSON (RFC 7946) or KML. Pure functions; the files are written by the commands.

Coordinates: WGS-84 degrees, GeoJSON order [longitude, latitude, altitude], rounded to 8
decimals (~1 mm; the geojson package's default 6 would round to ~0.1 m). A footprint is the
instance box's four lower corners, counter-clockwise seen from above (RFC 7946's exterior ring
rule), closed. Altitudes are metres above the georeference's ``height_ref`` (RFC 7946 heights
are ellipsoidal: an "msl" map's altitudes are labelled so in each feature's properties).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from xml.etree import ElementTree

import numpy as np

from ..scene.geodesy import Georeference
from .localize import Instance3D

PRECISION = 8  # decimals of every coordinate written (degrees: ~1 mm; metres: 10 nm)
NAN4 = ((math.nan, math.nan),) * 4


@dataclass(frozen=True)
class GeoInstance:
    """One 3D instance with its place on the Earth (NaN fields: the map has no georeference)."""

    rank: int  # 0: the largest instance
    gaussians: int
    box_min: tuple[float, float, float]  # map metres
    box_max: tuple[float, float, float]
    centre: tuple[float, float, float]  # map metres, the member Gaussians' mean
    latitude: float = math.nan  # WGS-84 degrees of ``centre``
    longitude: float = math.nan
    altitude: float = math.nan  # metres above the georeference's height_ref
    footprint: tuple[tuple[float, float], ...] = NAN4  # 4 x (lon, lat) lower box corners, CCW from above
    box_altitude: tuple[float, float] = (math.nan, math.nan)  # [lowest, highest] metres

    @property
    def located(self) -> bool:
        return math.isfinite(self.latitude) and math.isfinite(self.longitude)

    @property
    def extent(self) -> tuple[float, float, float]:
        """The box's size along the map's x, y, z, metres."""
        return tuple(float(b - a) for a, b in zip(self.box_min, self.box_max, strict=True))  # type: ignore[return-value]


def locate(instances: Sequence[Instance3D], georef: Georeference | None) -> list[GeoInstance]:
    """The instances (map metres) with their centre, footprint and box altitudes on the Earth;
    without ``georef`` the geodetic fields are NaN."""
    located = []
    for rank, inst in enumerate(instances):
        plain = GeoInstance(
            rank, int(inst.gaussians), _triple(inst.box_min), _triple(inst.box_max), _triple(inst.centre)
        )
        if georef is None:
            located.append(plain)
            continue
        (x0, y0, z0), (x1, y1, z1) = inst.box_min, inst.box_max
        points = [inst.centre, (x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0), (x0, y0, z1)]
        lat, lon, alt = georef.to_geodetic(np.asarray(points, np.float64))
        corners = [(float(lon[i]), float(lat[i])) for i in range(1, 5)]
        if _signed_area(corners) < 0:  # a map frame with a reflection (EPSG transform): turn it round
            corners.reverse()
        located.append(
            GeoInstance(
                rank,
                plain.gaussians,
                plain.box_min,
                plain.box_max,
                plain.centre,
                float(lat[0]),
                float(lon[0]),
                float(alt[0]),
                tuple(corners),
                (float(min(alt[1], alt[5])), float(max(alt[1], alt[5]))),
            )
        )
    return located


def from_records(records: Sequence[dict]) -> list[GeoInstance]:
    """The 3D instances of a ``QueryReply`` (``Instance`` records of kind "3d", msgs/schema.yaml)."""
    out = []
    for rank, r in enumerate(i for i in records if i["kind"] == "3d"):
        lons_lats = r["footprint"]
        out.append(
            GeoInstance(
                rank,
                int(r["n_gaussians"]),
                _triple(r["box_min"]),
                _triple(r["box_max"]),
                _triple(r["centroid"]),
                float(r["latitude"]),
                float(r["longitude"]),
                float(r["altitude"]),
                tuple((float(lons_lats[2 * k]), float(lons_lats[2 * k + 1])) for k in range(4)),
                (float(r["box_altitude"][0]), float(r["box_altitude"][1])),
            )
        )
    return out


def _triple(values) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return (x, y, z)


def _signed_area(ring: Sequence[tuple[float, float]]) -> float:
    """Shoelace area of an open ring in (lon, lat): positive when counter-clockwise."""
    return 0.5 * sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(ring, [*ring[1:], ring[0]], strict=True))


def properties(inst: GeoInstance, text: str, map_version: int, height_ref: str, total: int) -> dict:
    """A feature's properties: the query, the map version, the instance's rank, Gaussians and
    score (its share of the answer's 3D Gaussians, 0..1: what ranks it), its extent (metres along
    the map's x, y, z) and its heights (metres above ``height_ref``)."""
    dx, dy, dz = inst.extent
    return {
        "query": text,
        "centre": [round(inst.longitude, PRECISION), round(inst.latitude, PRECISION), round(inst.altitude, 3)],
        "map_version": int(map_version),
        "rank": inst.rank,
        "gaussians": inst.gaussians,
        "score": round(inst.gaussians / total, 6) if total else 0.0,
        "extent_m": [round(dx, 3), round(dy, 3), round(dz, 3)],
        "altitude": round(inst.altitude, 3),
        "altitude_min": round(inst.box_altitude[0], 3),
        "altitude_max": round(inst.box_altitude[1], 3),
        "height_ref": height_ref,
    }


def feature_collection(instances: Sequence[GeoInstance], text: str, map_version: int, height_ref: str):
    """A ``geojson.FeatureCollection``: one Feature per located instance, its geometry the
    footprint Polygon (closed, counter-clockwise, at the box's lowest altitude), its centre
    [lon, lat, alt] and the rest in ``properties`` (above). A plain Polygon rather than a
    GeometryCollection with a centre Point: QGIS makes one layer per geometry type, and
    QGroundControl's GeoJSON import takes polygons, lines and points, not collections.
    ValueError when an instance is not located (the map has no georeference)."""
    import geojson

    total = sum(i.gaussians for i in instances)
    features = []
    for inst in instances:
        if not inst.located:
            raise ValueError(f"3D instance #{inst.rank} has no latitude and longitude: the map has no georeference")
        ring = [(lon, lat, inst.box_altitude[0]) for lon, lat in (*inst.footprint, inst.footprint[0])]
        footprint = geojson.Polygon([ring], precision=PRECISION)
        features.append(
            geojson.Feature(
                id=inst.rank,
                geometry=footprint,
                properties=properties(inst, text, map_version, height_ref, total),
            )
        )
    return geojson.FeatureCollection(features, query=text, map_version=int(map_version))


def dumps_geojson(collection) -> str:
    """The FeatureCollection as JSON text (its ``is_valid`` checked first: ValueError with its errors)."""
    import geojson

    if not collection.is_valid:
        raise ValueError(f"invalid GeoJSON: {collection.errors()}")
    return geojson.dumps(collection, indent=1) + "\n"


def kml_document(instances: Sequence[GeoInstance], text: str, map_version: int, height_ref: str) -> str:
    """KML 2.2: one Placemark per located instance (a MultiGeometry of the centre Point and the
    footprint Polygon, both clamped to the ground; the properties as ExtendedData)."""
    ns = "http://www.opengis.net/kml/2.2"
    kml = ElementTree.Element("kml", xmlns=ns)
    doc = ElementTree.SubElement(kml, "Document")
    ElementTree.SubElement(doc, "name").text = f'"{text}", map version {map_version}'
    total = sum(i.gaussians for i in instances)
    for inst in instances:
        if not inst.located:
            raise ValueError(f"3D instance #{inst.rank} has no latitude and longitude: the map has no georeference")
        mark = ElementTree.SubElement(doc, "Placemark", id=f"instance-{inst.rank}")
        ElementTree.SubElement(mark, "name").text = f"#{inst.rank} {text}"
        data = ElementTree.SubElement(mark, "ExtendedData")
        for key, value in properties(inst, text, map_version, height_ref, total).items():
            field = ElementTree.SubElement(data, "Data", name=key)
            ElementTree.SubElement(field, "value").text = str(value)
        shapes = ElementTree.SubElement(mark, "MultiGeometry")
        point = ElementTree.SubElement(shapes, "Point")
        ElementTree.SubElement(point, "coordinates").text = _kml_coords([(inst.longitude, inst.latitude)])
        polygon = ElementTree.SubElement(shapes, "Polygon")
        outer = ElementTree.SubElement(ElementTree.SubElement(polygon, "outerBoundaryIs"), "LinearRing")
        ElementTree.SubElement(outer, "coordinates").text = _kml_coords([*inst.footprint, inst.footprint[0]])
    ElementTree.indent(kml)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ElementTree.tostring(kml, encoding="unicode") + "\n"


def _kml_coords(points: Sequence[tuple[float, float]]) -> str:
    return " ".join(f"{lon:.{PRECISION}f},{lat:.{PRECISION}f}" for lon, lat in points)
