"""``olsplat ground``: the ground station's client. ``query`` asks the drone's query server for a
text and prints the located instances (writing heatmap and mask PNGs over the view with
``--view`` and ``--out``); ``status`` prints every node's latest diagnostics."""

from __future__ import annotations

import argparse
import json
import math
import sys
import uuid
from dataclasses import replace
from pathlib import Path


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("ground", help="ground station: query the drone, show node status")
    commands = parser.add_subparsers(dest="ground_command", required=True, metavar="COMMAND")
    query = commands.add_parser("query", help="ask the query server for a text")
    query.add_argument(
        "text", nargs="?", default="", help='what to find, e.g. "red roof buildings" (with --since: may be left out)'
    )
    query.add_argument(
        "--since",
        default="",
        metavar="FLIGHT",
        help="what changed since this earlier flight (f0) of a per-flight map; with a text, what appeared",
    )
    query.add_argument("--gone", action="store_true", help="with --since and a text: what went away instead")
    query.add_argument("--view", default="", help="answer with a heatmap and mask over this view (name or index)")
    query.add_argument(
        "--out",
        type=Path,
        help="write the heatmap and mask PNGs here (needs --view): first the preview's (VIEW_TEXT_preview_*.png, "
        "at most 320 px, asked first and written as soon as it comes), then the full answer's",
    )
    query.add_argument("--negatives", help="comma-separated texts to beat (default: the server's)")
    query.add_argument(
        "--threshold",
        type=float,
        default=math.nan,
        help="mask = heatmap above this cosine (default: beat every negative)",
    )
    query.add_argument("--json", action="store_true", help="print the answer as JSON")
    query.add_argument(
        "--geojson",
        type=Path,
        metavar="FILE",
        help="write the 3D instances as GeoJSON in WGS-84 (the drone's map needs a georef.json)",
    )
    query.add_argument("--kml", type=Path, metavar="FILE", help="write the 3D instances as KML (as --geojson)")
    status = commands.add_parser("status", help="print every node's latest diagnostics")
    status.add_argument("--json", action="store_true", help="print the statuses as JSON")
    for sub in (query, status):
        sub.add_argument(
            "--connect",
            default="tcp://127.0.0.1:5600",
            help="the query server's endpoint (default tcp://127.0.0.1:5600)",
        )
        sub.add_argument(
            "--timeout", type=_positive_seconds, default=10.0, help="seconds to wait for the answer (default 10)"
        )
        sub.add_argument("--client-key", type=Path, help="CURVE: this client's secret key file (olsplat keys generate)")
        sub.add_argument("--server-key", type=Path, help="CURVE: the server's public key file")
        sub.set_defaults(run=run)
    web = commands.add_parser(
        "web",
        help="a browser page: the map in 3D, the flight, queries, heatmaps, status (viser)",
        description="Serve the ground station's page. With --connect it asks a running graph over the "
        "ground link (the query server's endpoint; CURVE with --client-key/--server-key): live during a "
        "flight. With --run DIR it reads a run folder on this machine: a post-flight review.",
    )
    source = web.add_mutually_exclusive_group(required=True)
    source.add_argument("--connect", help="the drone's query server, e.g. tcp://DRONE:5600 (a live flight)")
    source.add_argument("--run", dest="run_dir", type=Path, help="a run folder (the launch file's run_dir)")
    web.add_argument(
        "--map",
        type=Path,
        help="with --run: the prior map PLY the run was made with (default: the one the run recorded, "
        "RUN/store/prior_map.json, checked by its SHA-256; for older runs RUN/../flight/map/point_cloud.ply)",
    )
    web.add_argument("--client-key", type=Path, help="with --connect: CURVE secret key file of this ground station")
    web.add_argument("--server-key", type=Path, help="with --connect: CURVE public key file of the drone's server")
    web.add_argument(
        "--timeout", type=_positive_seconds, default=10.0, help="with --connect: seconds to wait for an answer (10)"
    )
    web.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    web.add_argument("--port", type=int, default=8080, help="TCP port of the page (default 8080)")
    web.add_argument(
        "--max-splats", type=int, default=300_000, help="splats drawn in the browser (default 300,000; <= 500,000)"
    )
    web.add_argument(
        "--negatives",
        help="the page's first negatives, comma-separated, editable on the page (default with --run: the "
        "flight's labels when its queries.json lies beside the map's folder, as the demo's; else the query "
        "server's: object, things, stuff, texture)",
    )
    web.add_argument(
        "--change-cuts",
        metavar="C,O,N[,A]",
        help="with --run: the 'since flight' answers' change rule, as olsplat query --change-cuts (default: the "
        "cuts chosen on 60-view flights; shorter flights need looser ones, docs/method.md)",
    )
    web.add_argument("--seconds", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    web.set_defaults(run=run_web)


def run_web(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..extras import require

    require("viser", "the browser page (olsplat ground web)")
    from ..ground.page import GroundPage, serve
    from ..query.splats import MAX_SPLATS

    if not 1 <= args.max_splats <= MAX_SPLATS:
        raise OlsplatInputError(
            f"--max-splats must be 1..{MAX_SPLATS:,} (what a browser draws smoothly), got {args.max_splats}"
        )
    negatives = args.negatives
    if args.connect:
        if args.change_cuts:
            raise OlsplatInputError("--change-cuts goes with --run: a live drone's cuts are its query server's")
        source, where = _link_source(args), args.connect
    else:
        source, where = _run_source(args), str(args.run_dir)
        negatives = negatives or _mission_negatives(source.prior_map)
    negatives = negatives or "object, things, stuff, texture"
    page = GroundPage(source, args.host, args.port, title=f"olsplat ground station - {where}", negatives=negatives)
    print(f"ground station: http://{args.host}:{page.port} (of {where}); Ctrl-C stops", flush=True)
    serve(page, args.seconds)
    return 0


def _run_source(args: argparse.Namespace):
    from ..errors import OlsplatInputError
    from ..ground.review import RunReview

    if args.client_key or args.server_key:
        raise OlsplatInputError("--client-key and --server-key go with --connect, not --run")
    if not args.run_dir.is_dir():
        raise OlsplatInputError(f"{args.run_dir}: no such run folder")
    prior = args.map or _recorded_prior_map(args.run_dir)
    if not prior.exists():
        raise OlsplatInputError(f"{prior}: prior map not found: give the PLY the run was made with (--map)")
    if args.change_cuts:
        from ..query.change import ChangeParams

        try:
            ChangeParams().with_cuts(args.change_cuts)
        except ValueError as exc:
            raise OlsplatInputError(f"--change-cuts {exc}") from None
    return RunReview(args.run_dir, prior, args.max_splats, change_cuts=args.change_cuts or "")


def _recorded_prior_map(run_dir: Path) -> Path:
    """The map the run's accumulator recorded (RUN/store/prior_map.json: path and SHA-256, checked
    here); a run without that record (made before it was written): RUN/../flight/map/point_cloud.ply,
    the demo's layout."""
    from ..storage.prior import recorded_prior_map

    return recorded_prior_map(run_dir / "store") or run_dir / ".." / "flight" / "map" / "point_cloud.ply"


def _mission_negatives(prior_map: Path) -> str | None:
    """The flight's label texts, comma-separated, when FLIGHT/queries.json lies beside the prior
    map's folder (FLIGHT/map/point_cloud.ply, a simulated flight's layout): a query must beat
    the other things the mission looks for, a sharper test than "object, things"."""
    from ..errors import OlsplatInputError
    from ..evaluate.scene_eval import label_texts, load_queries

    flight = Path(prior_map).resolve().parent.parent
    if not (flight / "queries.json").is_file():
        return None
    try:
        return ", ".join(label_texts(*load_queries(flight)))
    except OlsplatInputError as exc:
        print(f"note: the page's negatives are the query server's: {exc}", file=sys.stderr)
        return None


def _client(args: argparse.Namespace):
    """The ground link's client of ``--connect`` (CURVE with both key files); ZMQError on a
    malformed endpoint."""
    import zmq

    from ..errors import OlsplatInputError
    from ..transport import QueryClient, curve

    if bool(args.client_key) != bool(args.server_key):
        raise OlsplatInputError("CURVE needs both --client-key and --server-key")
    keys = curve.ClientKeys(args.client_key, args.server_key) if args.client_key else None
    return QueryClient(zmq.Context.instance(), args.connect, timeout_s=args.timeout, keys=keys)


def _link_source(args: argparse.Namespace):
    import zmq

    from ..errors import OlsplatInputError
    from ..ground.link import LinkSource

    if args.map:
        raise OlsplatInputError("--map goes with --run: over --connect the drone sends its prior map")
    try:
        client = _client(args)
    except zmq.ZMQError as exc:
        raise OlsplatInputError(f"cannot connect to {args.connect}: {zmq.strerror(exc.errno or 0)}") from None
    return LinkSource(client, args.max_splats)


def run(args: argparse.Namespace) -> int:
    import zmq

    from olsplat_msgs import QueryRequest, StatusRequest

    from ..errors import EXIT_FAILED, OlsplatInputError
    from ..transport import NoReply

    if args.ground_command == "query" and not args.text.strip() and not args.since:
        raise OlsplatInputError("the query text is empty (only --since may leave it out)")
    if args.ground_command == "query" and args.gone and not (args.since and args.text.strip()):
        raise OlsplatInputError("--gone needs --since and a text")
    try:
        client = _client(args)
    except zmq.ZMQError as exc:  # a malformed endpoint (no port, unknown transport): same exit as an unreachable one
        reason = zmq.strerror(exc.errno or 0)
        print(
            f"olsplat ground {args.ground_command}: error: cannot connect to {args.connect}: {reason}",
            file=sys.stderr,
        )
        return EXIT_FAILED
    request_id = uuid.uuid4().hex[:12]
    try:
        if args.ground_command == "status":
            reply = client.request(StatusRequest(request_id=request_id))
            return print_status(reply, args.json)
        if args.out and not args.view:
            raise OlsplatInputError("--out writes pictures over a view: give --view too")
        negatives = [t.strip() for t in args.negatives.split(",") if t.strip()] if args.negatives else []
        request = QueryRequest(
            request_id=request_id,
            text=args.text,
            view=args.view,
            heatmap=bool(args.view),
            threshold=args.threshold,
            negatives=negatives,
            since=args.since,
            gone=args.gone,
        )
        if args.out and not args.since:  # the view's pictures at once, small, then the full answer's
            preview = client.request(replace(request, request_id=f"{request_id}-preview", preview=True))
            if preview.status == "ok":
                _write_pictures(preview, args.out, args.threshold, args.json, "preview")
        reply = client.request(request)
        code = print_answer(reply, args.json, args.out, args.threshold)
        if reply.status == "ok" and (args.geojson or args.kml):
            write_reply_geo_files(reply, args.geojson, args.kml, as_json=args.json)
        return code
    except NoReply as exc:
        hint = (
            "is the drone's graph running? (olsplat launch drone, or olsplat demo); "
            "with CURVE, are --client-key and --server-key the right pair?"
        )
        print(f"olsplat ground {args.ground_command}: error: {exc}: {hint}", file=sys.stderr)
        return EXIT_FAILED
    finally:
        client.close()


def write_reply_geo_files(reply, geojson_path: Path | None, kml_path: Path | None, as_json: bool = False) -> None:
    """A reply's 3D instances as GeoJSON / KML (their latitude, longitude and footprint come from
    the drone: its map's georef.json); refused in one line when the drone's map has none."""
    from ..errors import OlsplatInputError
    from ..query.geojson import from_records
    from .answers import write_geo_files

    if not reply.height_ref:
        raise OlsplatInputError(
            "--geojson and --kml need the drone's map to have a georeference (georef.json beside its PLY or in the "
            "run's map folder: olsplat map georef); the answer is in map coordinates only"
        )
    located = from_records(reply.instances)
    log = (lambda line: print(line, file=sys.stderr)) if as_json else print  # stdout holds the JSON
    write_geo_files(geojson_path, kml_path, located, reply.text, reply.map_version, reply.height_ref, log)


def print_status(reply, as_json: bool) -> int:
    if as_json:
        print(json.dumps({"map_version": reply.map_version, "nodes": reply.nodes}, indent=1, default=str))
        return 0
    print(f"map version {reply.map_version}")
    for node in reply.nodes:
        v = node.get("values", {})
        print(
            f"  {node['node']:16s} {_level_names().get(node['level'], node['level']):5s} age {node['age_s']:5.1f} s  "
            f"rate {v.get('rate_hz', 0):5.2f} Hz  latency {v.get('latency_ms', 0):8.1f} ms  "
            f"handled {v.get('handled', 0):5d}  drops {v.get('dropped', 0) + v.get('gaps', 0):4d}  bad "
            f"{v.get('bad_messages', 0):3d}  {node['message']}"
            + (f"  [restarts {v['restarts']}, last exit: {v.get('last_exit', '?')}]" if v.get("restarts") else "")
        )
    return 0


def print_answer(reply, as_json: bool, out: Path | None, threshold: float = math.nan) -> int:
    if as_json:
        print(
            json.dumps(
                {
                    "status": reply.status,
                    "message": reply.message,
                    "text": reply.text,
                    "view": reply.view,
                    "map_version": reply.map_version,
                    "height_ref": reply.height_ref,
                    **({"since": reply.since, "now": reply.now} if reply.since else {}),
                    # JSON has no NaN: a map without a georeference gives null latitudes
                    "instances": [{k: _finite_or_none(v) for k, v in i.items()} for i in _scored(reply)],
                    "seconds": reply.seconds,
                },
                indent=1,
            )
        )
    if reply.status != "ok":
        if not as_json:
            print(f'"{reply.text}": {reply.status}: {reply.message}')
        return 0 if reply.status == "no_map" else 1
    if not as_json:
        found3d = [i for i in reply.instances if i["kind"] == "3d"]
        found2d = [i for i in reply.instances if i["kind"] == "2d"]
        print(
            f'"{reply.text}" (map version {reply.map_version}, {reply.seconds:.2f} s): {reply.message}; '
            f"{len(found3d)} instances in 3D"
        )
        for inst in _scored(reply)[: len(found3d)][:20]:
            c, lo, hi = inst["centroid"], inst["box_min"], inst["box_max"]
            where = f", lat {inst['latitude']:.7f} lon {inst['longitude']:.7f}" if reply.height_ref else ""
            print(
                f"  3D #{inst['id']}: centre ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}) m{where}, box {hi[0] - lo[0]:.1f} x "
                f"{hi[1] - lo[1]:.1f} x {hi[2] - lo[2]:.1f} m, {inst['n_gaussians']} Gaussians"
                + (f", median change score {inst['score']:.2f}" if "score" in inst else "")
            )
        if reply.view:
            print(f"view {reply.view}: {len(found2d)} regions")
            for inst in found2d[:20]:
                print(f"  2D #{inst['id']}: box {tuple(inst['box2d'])}, {inst['area_px']} px")
    if out is not None:
        _write_pictures(reply, out, threshold, as_json)
    return 0


def _write_pictures(reply, out: Path, threshold: float, as_json: bool, kind: str = "") -> None:
    """A reply's heatmap and mask pictures into ``out`` (``viz.write_query_pictures``), if it has them."""
    from ..viz import write_query_pictures

    if reply.heatmap is None or reply.image is None or reply.mask is None:
        return
    alpha = (reply.heatmap != 0).astype("float32")  # the server sends 0 where nothing was rendered
    boxes = [tuple(i["box2d"]) for i in reply.instances if i["kind"] == "2d"]
    paths = write_query_pictures(
        out,
        reply.view,
        reply.text,
        reply.image,
        reply.heatmap,
        alpha,
        reply.mask,
        boxes,
        map_version=reply.map_version,
        threshold=threshold,
        kind=kind,
    )
    if not as_json:
        label = f"{kind} pictures" if kind else "pictures"
        print(f"{label} -> {', '.join(str(p) for p in paths)}")


def _scored(reply) -> list[dict]:
    """The reply's instances, a change query's 3D ones with their median change ``score``."""
    scores = reply.change_scores if reply.change_scores is not None else []
    return [
        {**inst, "score": round(float(scores[inst["id"]]), 4)} if inst["kind"] == "3d" and len(scores) else inst
        for inst in reply.instances
    ]


def _finite_or_none(value):
    """A record's value for JSON: NaN (no georeference) as None, in lists too."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    return value


def _level_names() -> dict:
    from ..transport.diagnostics import LEVEL_NAMES  # zmq and the codec: not for `--help`

    return LEVEL_NAMES


def _positive_seconds(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text}")
    return value
