"""``olsplat query``: one text against a language map: heatmap, mask and located instances (in
WGS-84 too, and as GeoJSON or KML, when the map has a georeference)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "query",
        help="ask a language map for a text: heatmap, mask, instances",
        epilog='examples:\n  olsplat query --map maps/ols/language_map.npz --scene scene "red roof buildings" '
        '--view 3 --out q/\n  olsplat query --map m.npz --scene scene road --negatives "trees,lawn,cars" '
        '--cluster-radius 3\n  olsplat query --map run/map --scene flight "red roof buildings" --geojson roofs.geojson '
        "--kml roofs.kml\n"
        "  olsplat query --map ab/flights/f1 --since ab/flights/f0 --scene B --json changes.json\n"
        '  olsplat query --map ab/flights/f1 --since ab/flights/f0 --scene B "cars" --view 3 --out q/\n'
        '  olsplat query --map ab/flights/f1 --since ab/flights/f0 --scene B "trees" --gone',
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--map",
        required=True,
        type=Path,
        help="language_map.npz (olsplat aggregate); a run's map folder (RUN/map: its latest snapshot); or the "
        "--out folder of olsplat aggregate --tile-m: then the query goes to each tile's map in turn and their 3D "
        "instances are gathered (no view is rendered)",
    )
    parser.add_argument("--scene", required=True, type=Path, help="the scene the map was made from")
    parser.add_argument(
        "text",
        nargs="?",
        help='what to find, e.g. "red roof buildings"; with --since: what appeared (or with --gone: went), and '
        "without it every change",
    )
    parser.add_argument(
        "--since",
        type=Path,
        metavar="MAP",
        help="what changed since an earlier flight: MAP and --map are two flights' maps of olsplat aggregate "
        "--per-flight (OUT/flights/f0, OUT/flights/f1 or their language_map.npz) and --scene the later flight; "
        "no TEXT: every change instance ranked by change score; TEXT: what moved towards it (docs/method.md, "
        "'Maps per flight and what changed')",
    )
    parser.add_argument(
        "--gone", action="store_true", help="with --since and TEXT: what matched TEXT before and no longer does"
    )
    parser.add_argument("--json", type=Path, metavar="FILE", help="with --since: write the change instances here")
    parser.add_argument(
        "--change-cuts",
        metavar="C,O,N[,A]",
        help="with --since: the change rule's candidate cut, object cut, fewest Gaussians and least ground area "
        "(m², 0 when left out) of an instance (defaults 1.654,2.48,10,2 without TEXT and 0.8,1.6,32 with it, "
        "chosen on 60-view flights; shorter flights need looser cuts, e.g. 1.4,1.8,10: docs/method.md)",
    )
    parser.add_argument("--view", help="view to render (name or index; default: the first)")
    parser.add_argument(
        "--negatives", help="comma-separated texts to beat (default: the scene's other queries, else canonical)"
    )
    parser.add_argument("--out", type=Path, help="write heatmap and mask PNGs here")
    parser.add_argument(
        "--cluster-radius",
        type=float,
        metavar="M",
        help="3D instances: chosen Gaussians closer than this (metres) join one instance (default: from the "
        "map's density, 2 x spacing x sqrt(min-points / pi), at least 1.5 m)",
    )
    parser.add_argument(
        "--min-points",
        type=int,
        help="3D instances: the fewest Gaussians that make one (default 20; with --since, the change rule's)",
    )
    parser.add_argument(
        "--geojson",
        type=Path,
        metavar="FILE",
        help="write the 3D instances as GeoJSON: one Feature each, its centre Point and footprint Polygon in WGS-84 "
        "(needs the map's georef.json: olsplat map georef)",
    )
    parser.add_argument("--kml", type=Path, metavar="FILE", help="write the 3D instances as KML (as --geojson)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..evaluate.scene_eval import label_texts, load_queries
    from ..outputs import output_folder
    from ..pipeline import Scene
    from ..query.answer import answer_query, encoder_for_map
    from ..query.geojson import locate
    from ..query.negatives import vocabulary_negatives
    from ..query.tiled import answer_tiled, is_tiled, tile_maps
    from ..scene import read_ply, select_view
    from ..storage.snapshot import LanguageMap
    from ..viz import write_query_pictures
    from .answers import height_ref, map_georef, print_instances, snapshot_of, write_geo_files

    if args.since is not None:
        from .query_change import run_change

        return run_change(args)
    for given, option in ((args.gone, "--gone"), (args.json, "--json"), (args.change_cuts, "--change-cuts")):
        if given:
            raise OlsplatInputError(f"{option} needs --since (a change query)")
    text = (args.text or "").strip()
    if not text:
        raise OlsplatInputError("the query text is empty")
    args.min_points = 20 if args.min_points is None else args.min_points
    if args.out:
        output_folder(args.out)
    scene = Scene.open(args.scene)
    tiled = args.map.is_dir() and is_tiled(args.map)
    if tiled and not tile_maps(args.map):
        raise OlsplatInputError(f"{args.map}: a tiled map whose tiles hold no map yet (was its aggregation stopped?)")
    map_file, version = (args.map, 0) if tiled else snapshot_of(args.map)
    georef = map_georef(scene.ply, args.map, needed=bool(args.geojson or args.kml))
    gaussians = read_ply(scene.ply)
    language_map = LanguageMap.load(tile_maps(args.map)[0] if tiled else map_file)  # a tile's: its encoder
    if args.negatives:
        negatives = [t.strip() for t in args.negatives.split(",") if t.strip()]
    elif (scene.folder / "queries.json").exists():
        labels, queries = load_queries(scene.folder)
        negatives = [t for t in label_texts(labels, queries) if t != text]
    else:
        negatives = vocabulary_negatives(text, encoder_for_map(language_map))
    camera = select_view(scene.cameras, args.view if args.view is not None else 0)
    if not ((args.cluster_radius is None or args.cluster_radius > 0) and args.min_points >= 1):
        raise OlsplatInputError(
            f"--cluster-radius must be > 0 and --min-points >= 1, got {args.cluster_radius} and {args.min_points}"
        )
    if tiled:
        tiled_answer = answer_tiled(
            args.map,
            gaussians,
            encoder_for_map(language_map),
            text,
            negatives,
            args.cluster_radius,
            args.min_points,
        )
        _print_tiled(tiled_answer, georef)
        write_geo_files(
            args.geojson, args.kml, locate(tiled_answer.instances, georef), text, version, height_ref(georef)
        )
        return 0
    answer = answer_query(
        language_map,
        gaussians,
        encoder_for_map(language_map),
        text,
        negatives,
        camera,
        cluster_radius=args.cluster_radius,
        min_points=args.min_points,
    )
    assert answer.mask is not None  # answered over a view: camera is given
    print(
        f'"{text}": {answer.chosen_count:,} Gaussians pick it over {len(answer.negatives)} negatives; '
        f"{len(answer.instances)} instances in 3D"
    )
    print_instances(answer.instances, georef)
    write_geo_files(args.geojson, args.kml, locate(answer.instances, georef), text, version, height_ref(georef))
    if answer.unknown_words:
        words = ", ".join(f'"{w}"' for w in answer.unknown_words)
        print(
            f"note: the encoder does not know {words}: to it they are all one unknown word, so they "
            f"cannot steer the answer ({language_map.encoder}; the shipped encoders know the simulator's "
            "words only: roofs, roads, lawns, trees, cars...)"
        )
    print(f"view {camera.name}: {int(answer.mask.sum()):,} pixels, {len(answer.regions)} regions")
    for i, region in enumerate(answer.regions[:20]):
        print(f"  2D #{i}: box {region.box}, {region.pixels} px")
    if args.out:
        paths = write_query_pictures(
            args.out, camera.name, text, scene.image(camera), answer.heatmap, answer.alpha, answer.mask, answer.regions
        )
        print(f"pictures -> {', '.join(str(p) for p in paths)}")
    return 0


def _print_tiled(answer, georef=None) -> None:
    """A tiled map's answer: the gathered instances, then each tile's share."""
    from .answers import print_instances

    print(
        f'"{answer.text}": {answer.chosen:,} Gaussians pick it over {len(answer.negatives)} negatives; '
        f"{len(answer.instances)} instances in 3D, from {len(answer.tiles)} tiles"
    )
    print_instances(answer.instances, georef)
    for name, (chosen, instances) in answer.tiles.items():
        print(f"  tile {name}: {chosen:,} Gaussians, {instances} instances")
