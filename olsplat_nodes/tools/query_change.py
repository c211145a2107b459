"""``olsplat query --map B --since A --scene FLIGHT_B [TEXT] [--gone]``: what changed between two
flights' maps of one prior map (``olsplat aggregate --per-flight``): without TEXT every change
instance ranked by change score; with TEXT what moved towards it ("appeared", the default) or
away from it (``--gone``). The method is ``query/change.py``."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import OlsplatInputError

if TYPE_CHECKING:  # the method loads when a change query runs: olsplat --help stays fast
    from ..query.change import ChangeParams
    from ..query.change_answer import ChangeAnswer


def flight_map_file(path: Path, option: str) -> Path:
    """The language map file of ``--map``/``--since``: a file as it is; a folder holding a
    language_map.npz (``OUT/flights/f1``), that file; a run's map folder, its newest snapshot."""
    from .answers import snapshot_of

    if path.is_dir():
        inside = path / "language_map.npz"
        return inside if inside.is_file() else snapshot_of(path)[0]
    if not path.exists():
        raise OlsplatInputError(f"{option} {path}: does not exist")
    return path


def load_flight_pair(later: Path, earlier: Path, prior_gaussians: int):
    """(map of the earlier flight, map of the later one), both checked: evidence fields (a
    per-flight map) and one prior map (the same Gaussian count, also the scene's)."""
    from ..query.change_answer import check_flight_map
    from ..storage import LanguageMap

    maps = []
    for path, option in ((earlier, "--since"), (later, "--map")):
        language_map = LanguageMap.load(flight_map_file(path, option))
        maps.append(check_flight_map(language_map, f"{option} {path}", prior_gaussians))
    return maps[0], maps[1]


def instance_records(answer: ChangeAnswer, georef) -> list[dict]:
    """The instances as JSON records: rank, map metres, Gaussians, median score, WGS-84 when known."""
    from ..query.geojson import locate

    records = []
    for inst, place in zip(answer.instances, locate(answer.instances, georef), strict=True):
        record = {
            "rank": place.rank,
            "centre": list(inst.centre),
            "box_min": list(inst.box_min),
            "box_max": list(inst.box_max),
            "gaussians": inst.gaussians,
            "score": round(float(inst.score), 4),
        }
        if place.located:
            record |= {"latitude": place.latitude, "longitude": place.longitude, "altitude": place.altitude}
        records.append(record)
    return records


def run_change(args: argparse.Namespace) -> int:
    from ..evaluate.scene_eval import label_texts, load_queries
    from ..outputs import output_folder
    from ..pipeline import Scene
    from ..query.change import TEXT_PARAMS, ChangeParams
    from ..query.change_answer import answer_change
    from ..query.geojson import locate
    from ..query.negatives import AERIAL_VOCABULARY
    from ..scene import read_ply, select_view
    from .answers import height_ref, map_georef, print_instances, write_geo_files

    text = args.text.strip() if args.text is not None else None
    if text == "":
        raise OlsplatInputError("the query text is empty (leave it out for what changed)")
    if args.out:
        output_folder(args.out)
    scene = Scene.open(args.scene)
    gaussians = read_ply(scene.ply)
    map_a, map_b = load_flight_pair(args.map, args.since, len(gaussians))
    georef = map_georef(scene.ply, args.map, needed=bool(args.geojson or args.kml))
    params = ChangeParams() if text is None else TEXT_PARAMS
    if args.change_cuts is not None:
        params = _with_cuts(params, args.change_cuts)
    if args.cluster_radius is not None or args.min_points is not None:
        if not ((args.cluster_radius is None or args.cluster_radius > 0) and (args.min_points or 1) >= 1):
            raise OlsplatInputError(
                f"--cluster-radius must be > 0 and --min-points >= 1, got {args.cluster_radius} and {args.min_points}"
            )
        params = ChangeParams(
            **{
                **asdict(params),
                "cluster_radius": args.cluster_radius or params.cluster_radius,
                "min_points": args.min_points or params.min_points,
            }
        )
    negatives = [t.strip() for t in args.negatives.split(",") if t.strip()] if args.negatives else None
    vocabulary = AERIAL_VOCABULARY
    if (scene.folder / "queries.json").exists():
        vocabulary = tuple(label_texts(*load_queries(scene.folder)))
    camera = select_view(scene.cameras, args.view) if args.view is not None or args.out else None
    if camera is None and args.out:
        camera = scene.cameras[0]
    answer = answer_change(map_a, map_b, gaussians, text, args.gone, negatives, vocabulary, params, camera)
    print(
        f"{answer.title} since {args.since}: {answer.scored:,} Gaussians seen well enough by both flights, "
        f"{answer.candidates:,} candidates; {len(answer.instances)} change instances"
    )
    if answer.negatives:
        print(f"  (the move must favour the text over: {', '.join(answer.negatives)})")
    print_instances(answer.instances, georef, scores=[i.score for i in answer.instances])
    title = answer.title if text is not None else "what changed"
    write_geo_files(args.geojson, args.kml, locate(answer.instances, georef), title, 0, height_ref(georef))
    if args.json:
        output_folder(Path(args.json).parent, "--json", given=Path(args.json))
        record = {
            "map": str(args.map),
            "since": str(args.since),
            "text": text,
            "direction": answer.direction,
            "negatives": answer.negatives,
            "params": asdict(answer.params),
            "scored": answer.scored,
            "candidates": answer.candidates,
            "instances": instance_records(answer, georef),
        }
        Path(args.json).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
        print(f"{len(answer.instances)} instances -> {args.json}")
    if args.out and camera is not None and answer.heatmap is not None:
        paths = write_change_pictures(args.out, camera, scene.image(camera), answer, str(args.since))
        print(f"pictures -> {', '.join(str(p) for p in paths)}")
    return 0


def write_change_pictures(folder: Path, camera, photo: np.ndarray, answer: ChangeAnswer, since: str) -> list[Path]:
    """VIEW_changed_heatmap.png (or VIEW_TEXT_appeared/gone_heatmap.png) and its mask: the change
    heatmap over the later flight's view, coloured 0 .. the object threshold x 2 (a fixed scale:
    a view without change stays blue), the mask where it exceeds the candidate cut."""
    from ..query.localize import regions_in_view
    from ..viz import query_pictures, safe_name, write_png

    assert answer.heatmap is not None and answer.alpha is not None
    heat = answer.heatmap
    valid = (answer.alpha > 0.5) & np.isfinite(heat)
    mask = valid & (np.nan_to_num(heat, nan=0.0) > answer.params.candidate)
    regions = regions_in_view(mask)
    caption = f"{answer.title} since {Path(since).name or since} on {Path(camera.name).name}; mask: score > "
    caption += f"{answer.params.candidate:g}"
    top = 2.0 * answer.params.object_score
    pictures = query_pictures(
        photo,
        np.nan_to_num(heat, nan=0.0),
        valid,
        mask,
        [r.box for r in regions],
        caption,
        scale=(0.0, top),
        unit="score",
    )
    stem = f"{safe_name(Path(camera.name).stem)}_{safe_name(answer.title if answer.text else 'changed')}"
    paths = [Path(folder) / f"{stem}_heatmap.png", Path(folder) / f"{stem}_mask.png"]
    for path, picture in zip(paths, pictures, strict=True):
        write_png(path, picture)
    return paths


def _with_cuts(params: ChangeParams, text: str) -> ChangeParams:
    """``params`` with ``--change-cuts C,O,N[,A]`` (``ChangeParams.with_cuts``)."""
    try:
        return params.with_cuts(text)
    except ValueError as exc:
        raise OlsplatInputError(f"--change-cuts {exc}") from None
