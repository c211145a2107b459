"""``olsplat bench diagnose``: what an evaluation world is like, in the statistics that decide
whether it can tell the paper's parts apart, for simulated flights and for real photos.

Sources: ``--scene S`` (an annotated flight: ``olsplat sim make``) gives every statistic;
``--photos DIR`` (a folder of real UAV photos in flight order) gives the label-free ones: how
the same ground patch changes between overlapping frames, and the flight's altitude profile
(EXIF GPS). The top-level sections pool the scenes; ``sources.<name>`` holds each source.

- ``encoders.<name>.region_accuracy`` and ``.accuracy_by_obliqueness`` (per off-nadir bin of the
  region's centre, degrees): each encoder alone on the finest regions, labelled with the
  nearest of the scene's label texts (``evaluate/diagnose/flight.py``);
- ``pair.*``: how the two encoders' region errors go together (``agreement.pair_statistics``);
- ``surfaces.*``: whether the first encoder's errors on a surface repeat over the views that see
  it (``agreement.surface_statistics``; ``surfaces_by_encoder`` for each encoder);
- ``patches.*``: ground patches tracked between consecutive frames by a ground-plane homography
  (``evaluate/diagnose/patches.py``): colour and sharpness change, and how often the first
  encoder's label of the same patch flips;
- ``flight.*``: the viewpoint's variation (camera heights and tilt; EXIF altitude for photos);
  ``relative_tilt_deg`` (median, and ``_p90``): the tilt between consecutive views, read from the
  ground patches' homographies (``patches.relative_tilts_deg``; the lens from the scene's cameras
  or the first photo's EXIF), so it is measured the same way on real photos.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import time
from pathlib import Path
from typing import Any

# the control pair until the independent pair ships: the two shipped encoders
DEFAULT_PAIR = "olsplat-cnn64,olsplat-vit48"
OBLIQUENESS_BINS_DEG = (0, 10, 20, 30, 45, 90)


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "diagnose",
        help="statistics of a flight and its encoders: accuracy by view angle, error correlation of a pair, "
        "repeated errors per surface, ground-patch change between frames (also for real photos)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--scene", action="append", default=[], type=Path, help="an annotated scene folder; repeatable")
    parser.add_argument("--photos", action="append", default=[], type=Path,
                        help="a folder of real UAV photos in flight order (label-free); repeatable")  # fmt: skip
    parser.add_argument("--encoders", default=DEFAULT_PAIR, help="the encoder pair A,B (shipped names or folders)")
    parser.add_argument("--views", type=int, default=0, help="the first N views of each scene (0: all)")
    parser.add_argument("--min-ncc", type=float, default=0.9,
                        help="ground patches: least grey correlation after the warp (default 0.9)")  # fmt: skip
    parser.add_argument("--max-shift", type=int, default=2, metavar="PX",
                        help="ground patches: no shift up to PX px aligns better (0: no test; default 2)")  # fmt: skip
    parser.add_argument("--json", type=Path, help="write every figure here")
    parser.add_argument("--md", type=Path, help="write the summary table here")
    parser.epilog = (
        "examples:\n"
        "  olsplat bench diagnose --scene small0 --scene small1 --json diag.json --md diag.md\n"
        "  olsplat bench diagnose --photos ../shared/data/caliterra --scene small0"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError

    if not args.scene and not args.photos:
        raise OlsplatInputError("bench diagnose: give at least one --scene or --photos folder")
    names = [n.strip() for n in args.encoders.split(",") if n.strip()]
    if len(names) != 2:
        raise OlsplatInputError(f"--encoders: give two encoders A,B, got {args.encoders!r}")
    if not -1.0 <= args.min_ncc <= 1.0 or args.max_shift < 0:
        raise OlsplatInputError(
            f"--min-ncc must be in [-1, 1] and --max-shift >= 0, got {args.min_ncc}, {args.max_shift}"
        )
    gate = {"min_ncc": args.min_ncc, "max_shift_px": args.max_shift}
    report = diagnose(args.scene, args.photos, names, args.views, gate)
    table = summary_markdown(report)
    print(table)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=_plain))
    if args.md:
        args.md.write_text(table + "\n")
    return 0


def _plain(value: Any) -> Any:
    """NumPy scalars in the report as JSON numbers."""
    return value.item() if hasattr(value, "item") else str(value)


def diagnose(
    scenes: list[Path], photos: list[Path], encoder_names: list[str], views: int = 0, gate: dict | None = None
) -> dict:
    """The report (see the module's docstring): pooled sections over ``scenes`` and one entry
    per source under ``sources``. ``gate``: ``ground_patch_pairs``' ``min_ncc`` / ``max_shift_px``
    (default: its own), recorded in the report as ``patch_gate``."""
    gate = {"min_ncc": 0.9, "max_shift_px": 2, **(gate or {})}
    import numpy as np

    from ..encoders.spec import encoder_from_spec
    from ..evaluate.diagnose.agreement import (
        accuracy_by_bins,
        pair_statistics,
        region_accuracy,
        surface_statistics,
    )
    from ..evaluate.diagnose.flight import FlightRecords, collect_flight, flight_geometry
    from ..evaluate.diagnose.patches import (
        ground_patch_pairs,
        label_of_encoder,
        patch_statistics,
        read_flight_images,
        relative_tilts_deg,
    )
    from ..sources.exif import focal_length_px, read_exif

    def tilt_section(pairs, focal_px: float, centre: tuple[float, float]) -> dict:
        """The tilt between consecutive views (degrees): median and p90 over the frame pairs."""
        tilts = relative_tilts_deg(pairs, focal_px, centre)
        if len(tilts) == 0:
            return {"relative_tilt_deg": float("nan"), "relative_tilt_deg_p90": float("nan")}
        return {"relative_tilt_deg": float(np.median(tilts)), "relative_tilt_deg_p90": float(np.percentile(tilts, 90))}

    from ..evaluate.scene_eval import label_texts, load_queries
    from ..pipeline import Scene

    encoders = {name: encoder_from_spec(name) for name in encoder_names}
    first, second = encoder_names

    def encoder_section(records: list[FlightRecords]) -> dict:
        truth = np.concatenate([r.region_truth for r in records])
        angle = np.concatenate([r.region_off_nadir_deg for r in records])
        predicted = {n: np.concatenate([r.region_predicted[n] for r in records]) for n in encoder_names}
        surface_truth = np.concatenate([r.surface_truth for r in records])
        # surface ids are per scene: offset them so that two scenes' surfaces never merge
        surfaces = np.concatenate([r.surface + i * 10**15 for i, r in enumerate(records)])
        surface_errors = {
            n: np.concatenate([r.surface_predicted[n] for r in records]) != surface_truth for n in encoder_names
        }
        by_encoder = {n: surface_statistics(surfaces, surface_errors[n]) for n in encoder_names}
        return {
            "encoders": {
                n: {
                    "region_accuracy": region_accuracy(truth, predicted[n]),
                    "accuracy_by_obliqueness": accuracy_by_bins(truth, predicted[n], angle, OBLIQUENESS_BINS_DEG),
                    "regions": len(truth),
                }
                for n in encoder_names
            },
            "pair": {"encoders": [first, second], **pair_statistics(truth, predicted[first], predicted[second])},
            "surfaces": {"encoder": first, **by_encoder[first]},
            "surfaces_by_encoder": by_encoder,
        }

    sources: dict[str, dict] = {}
    records, all_pairs = [], []
    for folder in scenes:
        started = time.perf_counter()
        scene = Scene.open(folder)
        cameras = scene.cameras[:views] if views else scene.cameras
        record = collect_flight(scene.folder, cameras, scene.image, encoders)
        labels, queries = load_queries(scene.folder)
        pairs = ground_patch_pairs([scene.image(c) for c in cameras], **gate)
        label_of = label_of_encoder(encoders[first], label_texts(labels, queries))
        records.append(record)
        all_pairs.append((pairs, label_of))
        sources[folder.name] = {
            "kind": "scene",
            "folder": str(folder),
            "flight": {
                **flight_geometry(cameras),
                **tilt_section(pairs, cameras[0].fx, (cameras[0].cx - 0.5, cameras[0].cy - 0.5)),
            },  # OpenCV pixels
            **encoder_section([record]),
            "patches": patch_statistics(pairs, label_of),
            "seconds": time.perf_counter() - started,
        }
    for folder in photos:
        started = time.perf_counter()
        images = read_flight_images(folder)
        pairs = ground_patch_pairs(images, **gate)
        label_of = label_of_encoder(encoders[first], list(_default_label_texts()))
        flight = photo_altitudes(folder)
        try:  # the first photo's lens (EXIF), at the stored image's size
            photo = read_exif(sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))[0])
            height, width = images[0].shape[:2]
            flight.update(tilt_section(pairs, focal_length_px(photo)[0], ((width - 1) / 2, (height - 1) / 2)))
        except (IndexError, ValueError):  # no JPEG or no focal length in its EXIF: no tilt figure
            pass
        sources[folder.name] = {
            "kind": "photos",
            "folder": str(folder),
            "flight": flight,
            "patches": patch_statistics(pairs, label_of),
            "seconds": time.perf_counter() - started,
        }
    report: dict[str, Any] = {"encoder_pair": encoder_names, "patch_gate": gate, "sources": sources}
    if records:
        report.update(encoder_section(records))
        # each flight's frame pairs apart: frame pair (0, 1) of two flights has two exposure gains
        pooled = [dataclasses.replace(p, flight=k) for k, (pairs, _) in enumerate(all_pairs) for p in pairs]
        report["patches"] = patch_statistics(pooled, all_pairs[0][1])  # one label vocabulary: the first scene's
    return report


def _default_label_texts() -> tuple[str, ...]:
    """Label texts for photos, which carry no queries.json: the simulator's vocabulary, as a
    query would word each label (the shipped encoders were trained on it)."""
    from olsplat_sim.zeroshot import label_queries

    return tuple(label_queries())


def photo_altitudes(folder: Path) -> dict[str, Any]:
    """The EXIF GPS altitude (metres above mean sea level) of each photo, in name order, and
    its range and largest step; photos without one are skipped."""
    from ..sources.exif import read_exif

    altitudes = []
    for path in sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg")):
        photo = read_exif(path)
        if photo.alt is not None:
            altitudes.append(float(photo.alt))
    if not altitudes:
        return {"views": 0}
    steps = [abs(b - a) for a, b in itertools.pairwise(altitudes)]
    return {
        "views": len(altitudes),
        "altitude_m": altitudes,
        "height_range_m": max(altitudes) - min(altitudes),
        "height_step_max_m": max(steps, default=0.0),
    }


def summary_markdown(report: dict) -> str:
    """One table: a row per statistic, a column per source (and the pooled scenes)."""
    columns = list(report["sources"])
    pooled = "encoders" in report
    header = ["statistic", *(["scenes pooled"] if pooled else []), *columns]
    first, second = report["encoder_pair"]

    def get(section: dict, path: str) -> str:
        value: Any = section
        for key in path.split("."):
            if not isinstance(value, dict) or key not in value:
                return ""
            value = value[key]
        return f"{value:.3f}" if isinstance(value, float) else str(value)

    rows = [
        f"encoders.{first}.region_accuracy",
        f"encoders.{second}.region_accuracy",
        "pair.phi",
        "pair.both_wrong",
        "pair.both_wrong_if_independent",
        "pair.same_wrong_label",
        "surfaces.error_icc",
        "surfaces.wrong_every_view",
        "surfaces.wrong_some_views",
        "patches.pairs",
        "patches.label_flip_rate",
        "patches.colour_change",
        "patches.colour_change_p90",
        "patches.colour_change_global",
        "patches.sharpness_change",
        "flight.height_range_m",
        "flight.tilt_median_deg",
        "flight.relative_tilt_deg",
        "flight.relative_tilt_deg_p90",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        cells = ([get(report, row)] if pooled else []) + [get(report["sources"][c], row) for c in columns]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
