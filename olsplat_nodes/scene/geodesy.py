"""WGS-84 geodesy and a map's georeference (``georef.json`` beside the map's PLY).

Frames:
- **Geodetic**: WGS-84 latitude and longitude in degrees, altitude in metres. The altitude is
  above the ellipsoid or above mean sea level, as the georeference's ``height_ref`` says (GPS,
  EXIF and PX4's ``alt`` are MSL; RFC 7946 GeoJSON heights are ellipsoidal).
- **NED** / **ENU**: local tangent frames at an origin, metres: +x north, +y east, +z down /
  +x east, +y north, +z up. A map's world frame is ENU (the simulator's town, the photo folder's
  and the autopilot's worlds), so a map is georeferenced by its origin alone.
- **EPSG**: a map whose world is a projected system (UTM, EPSG:326xx) or anything else pyproj
  knows, given by the EPSG code and a 4x4 ``crs_from_map`` (the optional ``geo`` extra).

``geodetic_to_ned`` is our own, exact through ECEF (what the telemetry and photo sources
use); ``enu_to_geodetic`` and ``geodetic_to_enu`` are pymap3d's (the tests hold ours to
pymap3d's within a millimetre).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..durable import write_atomic
from ..errors import SceneFormatError

# WGS-84 ellipsoid.
WGS84_A = 6378137.0  # semi-major axis, metres
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared

# Columns: NED axes written in ENU (x_enu = y_ned, y_enu = x_ned, z_enu = -z_ned).
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

GEOREF_FILE = "georef.json"  # beside the map's PLY (or in a run's map folder)
GEOREF_VERSION = 1
HEIGHT_REFS = ("ellipsoid", "msl")  # altitude above the WGS-84 ellipsoid, above mean sea level
AXES = ("enu", "epsg")


def geodetic_to_ned(lat_deg, lon_deg, alt_m, reference) -> np.ndarray:
    """WGS-84 latitude/longitude (degrees) and altitude (metres) -> [..., 3] NED metres.

    ``reference`` is (lat_deg, lon_deg, alt_m) of the NED origin. Exact through ECEF, no
    flat-earth approximation. Altitudes may be above mean sea level (MAVLink ``alt``) as long
    as the reference uses the same datum: the geoid offset is constant over a flight area.
    """
    lat0, lon0, alt0 = (float(v) for v in reference)
    ecef = _ecef(lat_deg, lon_deg, alt_m)
    ecef0 = _ecef(lat0, lon0, alt0)
    phi, lam = np.radians(lat0), np.radians(lon0)
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    ned_from_ecef = np.array([[-sp * cl, -sp * sl, cp], [-sl, cl, 0.0], [-cp * cl, -cp * sl, -sp]])
    return (ecef - ecef0) @ ned_from_ecef.T


def _ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """[..., 3] Earth-centred Earth-fixed metres."""
    phi = np.radians(np.asarray(lat_deg, np.float64))
    lam = np.radians(np.asarray(lon_deg, np.float64))
    h = np.asarray(alt_m, np.float64)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(phi) ** 2)  # prime vertical radius
    return np.stack(
        [
            (n + h) * np.cos(phi) * np.cos(lam),
            (n + h) * np.cos(phi) * np.sin(lam),
            (n * (1.0 - WGS84_E2) + h) * np.sin(phi),
        ],
        -1,
    )


def enu_to_geodetic(points_enu, origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, 3] ENU metres around ``origin`` (lat_deg, lon_deg, alt_m) -> (lat [N], lon [N], alt [N])
    in degrees and metres (pymap3d, WGS-84; the altitude in the origin's datum)."""
    import pymap3d

    points = np.asarray(points_enu, np.float64).reshape(-1, 3)
    lat, lon, alt = pymap3d.enu2geodetic(points[:, 0], points[:, 1], points[:, 2], *(float(v) for v in origin))
    return np.asarray(lat, np.float64), np.asarray(lon, np.float64), np.asarray(alt, np.float64)


def geodetic_to_enu(lat_deg, lon_deg, alt_m, origin) -> np.ndarray:
    """WGS-84 degrees and metres [N] -> [N, 3] ENU metres around ``origin`` (pymap3d)."""
    import pymap3d

    args = (np.asarray(v, np.float64).reshape(-1) for v in (lat_deg, lon_deg, alt_m))
    e, n, u = pymap3d.geodetic2enu(*args, *(float(v) for v in origin))
    return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], -1).astype(np.float64)


@dataclass(frozen=True)
class Georeference:
    """Where a map's world frame lies on the Earth.

    ``axes`` "enu": map x east, y north, z up, metres, from the origin ``latitude``,
    ``longitude`` (degrees) and ``altitude`` (metres, above ``height_ref``). ``axes`` "epsg": map
    points go through ``crs_from_map`` [4, 4] into the system ``epsg`` (x, y in its units, z the
    altitude; easting first for a projected system), then to WGS-84 with pyproj. ``source``: where
    the georeference came from, for the reader."""

    latitude: float = math.nan
    longitude: float = math.nan
    altitude: float = 0.0
    height_ref: str = "ellipsoid"
    axes: str = "enu"
    epsg: int = 0
    crs_from_map: np.ndarray | None = field(default=None, compare=False)  # [4, 4], axes "epsg" only
    source: str = ""

    def __post_init__(self) -> None:
        problem = self.problem()
        if problem:
            raise ValueError(problem)

    def problem(self) -> str | None:
        """What makes this georeference unusable, as "field: reason", or None."""
        if self.axes not in AXES:
            return f"axes: {self.axes!r}, expected one of {', '.join(AXES)}"
        if self.height_ref not in HEIGHT_REFS:
            return f"height_ref: {self.height_ref!r}, expected one of {', '.join(HEIGHT_REFS)}"
        if not math.isfinite(self.altitude):
            return f"altitude: {self.altitude!r} is not a finite number of metres"
        if self.axes == "enu":
            if not (math.isfinite(self.latitude) and -90.0 <= self.latitude <= 90.0):
                return f"latitude: {self.latitude!r} is not in -90..90 degrees"
            if not (math.isfinite(self.longitude) and -180.0 <= self.longitude <= 180.0):
                return f"longitude: {self.longitude!r} is not in -180..180 degrees"
            return None
        if self.epsg <= 0:
            return f"epsg: {self.epsg!r} is not an EPSG code"
        m = None if self.crs_from_map is None else np.asarray(self.crs_from_map, np.float64)
        if m is None or m.shape != (4, 4) or not np.isfinite(m).all():
            return "crs_from_map: expected 4 rows of 4 finite numbers"
        return None

    @property
    def origin(self) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_m) of the ENU origin."""
        return (self.latitude, self.longitude, self.altitude)

    def to_geodetic(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """[N, 3] map metres -> (lat [N], lon [N], alt [N]): WGS-84 degrees, metres above
        ``height_ref``."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if self.axes == "enu":
            return enu_to_geodetic(points, self.origin)
        return self._epsg_to_geodetic(points)

    def _epsg_to_geodetic(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        from ..extras import require

        require("pyproj", f"a map georeferenced in EPSG:{self.epsg}")
        from pyproj import Transformer

        assert self.crs_from_map is not None  # checked in __post_init__
        crs = points @ self.crs_from_map[:3, :3].T + self.crs_from_map[:3, 3]
        to_wgs84 = Transformer.from_crs(f"EPSG:{self.epsg}", "EPSG:4326", always_xy=True)
        lon, lat = to_wgs84.transform(crs[:, 0], crs[:, 1])
        return np.asarray(lat, np.float64), np.asarray(lon, np.float64), crs[:, 2].copy()

    def to_json(self) -> dict:
        """The ``georef.json`` document."""
        doc: dict = {"version": GEOREF_VERSION, "axes": self.axes}
        if self.axes == "enu":
            doc.update(latitude=self.latitude, longitude=self.longitude, altitude=self.altitude)
        else:
            assert self.crs_from_map is not None
            doc.update(epsg=self.epsg, crs_from_map=np.asarray(self.crs_from_map, float).tolist())
        doc.update(height_ref=self.height_ref, source=self.source)
        return doc

    @classmethod
    def from_json(cls, doc, where: str | Path = GEOREF_FILE) -> Georeference:
        """A georeference from its document; SceneFormatError naming ``where`` and the field."""
        if not isinstance(doc, dict):
            raise SceneFormatError(where, f"expected a JSON object, got {type(doc).__name__}")
        if doc.get("version") != GEOREF_VERSION:
            raise SceneFormatError(where, f"version: {doc.get('version')!r}, this reader knows {GEOREF_VERSION}")
        axes = doc.get("axes", "enu")
        if axes not in AXES:
            raise SceneFormatError(where, f"axes: {axes!r}, expected one of {', '.join(AXES)}")
        need = ("latitude", "longitude", "altitude") if axes == "enu" else ("epsg", "crs_from_map")
        for key in need:
            if key not in doc:
                raise SceneFormatError(where, f"{key}: missing (axes {axes!r} needs {', '.join(need)})")
        numbers = {}
        for key in ("latitude", "longitude", "altitude"):
            value = doc.get(key, math.nan if key != "altitude" else 0.0)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise SceneFormatError(where, f"{key}: {value!r} is not a number")
            numbers[key] = float(value)
        epsg = doc.get("epsg", 0)
        if isinstance(epsg, bool) or not isinstance(epsg, int):
            raise SceneFormatError(where, f"epsg: {epsg!r} is not an integer EPSG code")
        matrix = doc.get("crs_from_map")
        try:
            crs_from_map = None if matrix is None else np.array(matrix, np.float64)
        except (TypeError, ValueError):
            raise SceneFormatError(where, "crs_from_map: expected 4 rows of 4 numbers") from None
        try:
            return cls(
                **numbers,
                height_ref=str(doc.get("height_ref", "ellipsoid")),
                axes=str(axes),
                epsg=epsg,
                crs_from_map=crs_from_map,
                source=str(doc.get("source", "")),
            )
        except ValueError as exc:
            raise SceneFormatError(where, str(exc)) from None


def read_georef(path: str | Path) -> Georeference:
    """Read a ``georef.json``; SceneFormatError naming the file and the field when it is not one."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise SceneFormatError(path, f"cannot be read ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneFormatError(path, f"not JSON ({exc})") from None
    return Georeference.from_json(doc, path)


def write_georef(path: str | Path, georef: Georeference) -> Path:
    """Write ``georef`` as JSON to ``path`` (a file, or a folder to hold ``georef.json``)."""
    path = Path(path)
    if path.is_dir():
        path = path / GEOREF_FILE
    write_atomic(path, (json.dumps(georef.to_json(), indent=1) + "\n").encode())
    return path


def find_georef(*folders: str | Path) -> Path | None:
    """The first ``georef.json`` in ``folders`` (in the order given), or None."""
    for folder in folders:
        candidate = Path(folder) / GEOREF_FILE
        if candidate.is_file():
            return candidate
    return None
