"""What ``olsplat query`` and ``olsplat query --since`` share: the map file of ``--map``, the
map's georeference, the 3D instances printed and written as GeoJSON or KML."""

from __future__ import annotations

from pathlib import Path


def snapshot_of(path: Path) -> tuple[Path, int]:
    """(the language map file, its version) of ``--map``: a file as it is (version 0), a run's
    map folder as its newest snapshot (``latest.json``)."""
    from ..errors import OlsplatInputError
    from ..storage import latest_map

    if not path.is_dir():
        return path, 0
    record = latest_map(path)
    if record is None or "path" not in record:
        raise OlsplatInputError(
            f"{path}: a folder without latest.json: give a language_map.npz, a run's map folder or a tiled map's folder"
        )
    return Path(record["path"]), int(record.get("version", 0))


def map_georef(prior_map: Path, map_arg: Path, needed: bool):
    """The map's georeference: georef.json beside the prior map's PLY, else in the language map's
    folder (a run's, from its source); None when there is none and none is ``needed``."""
    from ..errors import OlsplatInputError
    from ..scene.geodesy import find_georef, read_georef

    path = find_georef(Path(prior_map).parent, map_arg if map_arg.is_dir() else map_arg.parent)
    if path is None:
        if needed:
            raise OlsplatInputError(
                f"--geojson and --kml need the map's georeference, and neither {Path(prior_map).parent} nor "
                f"{map_arg if map_arg.is_dir() else map_arg.parent} holds a georef.json: olsplat map georef "
                f"{Path(prior_map).parent} --origin LAT LON ALT gives it one"
            )
        return None
    return read_georef(path)


def height_ref(georef) -> str:
    return "" if georef is None else georef.height_ref


def write_geo_files(geojson_path, kml_path, located, text: str, version: int, height_ref: str, log=print) -> None:
    """Write the located 3D instances (``query.geojson.GeoInstance``) as GeoJSON and/or KML (a
    path None: not that one); ``height_ref`` "" means the map has no georeference: refused."""
    from ..errors import OlsplatInputError
    from ..outputs import output_folder
    from ..query.geojson import dumps_geojson, feature_collection, kml_document

    for path, option, make in (
        (geojson_path, "--geojson", lambda: dumps_geojson(feature_collection(located, text, version, height_ref))),
        (kml_path, "--kml", lambda: kml_document(located, text, version, height_ref)),
    ):
        if path is None:
            continue
        if not height_ref:
            raise OlsplatInputError(f"{option} needs the map's georeference (georef.json): olsplat map georef")
        if Path(path).is_dir():
            raise OlsplatInputError(f"{option} {path}: is a folder; give a file name")
        output_folder(Path(path).parent, option, given=Path(path))
        Path(path).write_text(make(), encoding="utf-8")
        log(f"{len(located)} instances -> {path}")


def print_instances(instances, georef=None, scores=None) -> None:
    """The first 20 instances, one line each; ``scores``: each one's median change score, added."""
    from ..query.geojson import locate

    scores = scores if scores is not None else [None] * len(instances)
    for inst, place, score in zip(instances[:20], locate(instances[:20], georef), scores[:20], strict=True):
        c, lo, hi = inst.centre, inst.box_min, inst.box_max
        where = f", lat {place.latitude:.7f} lon {place.longitude:.7f}" if place.located else ""
        print(
            f"  3D #{place.rank}: centre ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) m{where}, box {hi[0] - lo[0]:.1f} x "
            f"{hi[1] - lo[1]:.1f} x {hi[2] - lo[2]:.1f} m, {inst.gaussians} Gaussians"
            + (f", median change score {score:.2f}" if score is not None else "")
        )
