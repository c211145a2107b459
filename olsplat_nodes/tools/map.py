"""``olsplat map georef``: show or give a map its georeference (``georef.json`` beside its PLY),
so that its answers come out in WGS-84 (``olsplat query --geojson``, the query server's replies)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("map", help="a map's georeference: where it lies on the Earth")
    commands = parser.add_subparsers(dest="map_command", required=True, metavar="COMMAND")
    georef = commands.add_parser(
        "georef",
        help="show or write MAP/georef.json",
        description="Without --origin: print the map's georeference. With --origin: write georef.json "
        "beside the map's PLY: its world frame is ENU (x east, y north, z up, metres) around that origin.",
        epilog="examples:\n  olsplat map georef flight/map --origin 47.397742 8.545594 488\n"
        "  olsplat map georef flight/map/point_cloud.ply --origin 47.397742 8.545594 435.2 --height-ref msl\n"
        "  olsplat map georef flight/map",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    georef.add_argument("map", type=Path, help="the map's folder, or its PLY (georef.json goes beside it)")
    georef.add_argument(
        "--origin",
        nargs=3,
        type=float,
        metavar=("LAT", "LON", "ALT"),
        help="WGS-84 latitude and longitude (degrees) and altitude (metres) of the map's origin",
    )
    georef.add_argument(
        "--height-ref",
        choices=("ellipsoid", "msl"),
        default="ellipsoid",
        help="ALT is above the WGS-84 ellipsoid (default; GeoJSON's heights) or above mean sea level (GPS, EXIF)",
    )
    georef.add_argument("--force", action="store_true", help="replace a georef.json that is there")
    georef.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..scene.geodesy import GEOREF_FILE, Georeference, read_georef, write_georef

    folder = args.map if args.map.is_dir() else args.map.parent
    if not folder.is_dir():
        raise OlsplatInputError(f"{args.map}: no such map folder or file")
    path = folder / GEOREF_FILE
    if args.origin is None:
        if not path.is_file():
            raise OlsplatInputError(
                f"{path}: the map has no georeference: give one with olsplat map georef {args.map} --origin LAT LON ALT"
            )
        print(describe(read_georef(path), path))
        return 0
    lat, lon, alt = args.origin
    if not all(math.isfinite(v) for v in args.origin):
        raise OlsplatInputError(f"--origin needs finite numbers, got {lat} {lon} {alt}")
    try:
        georef = Georeference(lat, lon, alt, height_ref=args.height_ref, source="olsplat map georef --origin")
    except ValueError as exc:
        raise OlsplatInputError(f"--origin: {exc}") from None
    if path.exists() and not args.force:
        raise OlsplatInputError(f"{path} exists already: --force replaces it")
    write_georef(path, georef)
    print(describe(georef, path))
    return 0


def describe(georef, path: Path) -> str:
    """One line: where the map lies."""
    if georef.axes == "epsg":
        return f"{path}: EPSG:{georef.epsg} through crs_from_map, heights above {georef.height_ref}"
    return (
        f"{path}: ENU around lat {georef.latitude:.8f}, lon {georef.longitude:.8f}, {georef.altitude:.3f} m above "
        + ("the WGS-84 ellipsoid" if georef.height_ref == "ellipsoid" else "mean sea level")
        + (f" ({georef.source})" if georef.source else "")
    )
