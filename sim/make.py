"""``olsplat sim make``: one complete synthetic dataset, the way a user would have a real one.

Output folder (documented in sim/README.md):

    map/point_cloud.ply        the reconstructed map (INRIA PLY), what the method runs on
    map/georef.json            where the town lies on the Earth (``TOWN_GEOREF``)
    sparse/0/                  COLMAP text model: the SfM poses (with pose noise) of every image
    images/                    the frames as JPEG, + timestamps.csv (name, stamp_ns)
    annotations/<frame>.json   LabelMe polygons of the visible targets in each frame
    queries.json               evaluation queries: text, target labels, instance ids
    replay.mcap                the flight as a replay log (images, calibration, poses)
    replay_bag/                with ``bag``: the same flight as a ROS 2 bag (rosbag2 folder)
    truth/                     labels of every map Gaussian, the true scene and true poses
    preview/                   contact_sheet.jpg and overview.jpg
    scene.json                 how the dataset was made (preset, seed, flight seed, counts, parameters)

Everything is a pure function of (preset, seed, flight seed, options): same inputs, same bytes.
The town and its map depend on the seed alone; a flight seed flies the same town again on
another path (see ``_streams``), so that several flights of one map can be aggregated together.
``options.world`` (world.py) is the evaluation world: v1 (the default) or v2 (view-dependent
appearance, varying altitude, haze, cloud shadows, a calibrated camera).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from olsplat_nodes.raster import rasterize
from olsplat_nodes.scene import Camera, Gaussians, write_colmap, write_ply
from olsplat_nodes.scene.geodesy import Georeference, write_georef
from olsplat_nodes.sources import SourceFrame
from olsplat_nodes.sources.replay_log import encode_jpeg, read_replay, write_mcap, write_timestamps
from olsplat_nodes.sources.rosbag_write import write_rosbag2

from .annotate import annotate_view, label_maps
from .appearance import sun_vector, with_view_dependence
from .atmosphere import CloudField, apply_haze, shadow_light, surface_points
from .change_spec import ChangeSpec, change_summary, changes_rng
from .change_truth import change_mask, mark_map, write_changes, write_mask
from .changes import apply_changes
from .flight import EPOCH_NS, FlightFrame, FlightSpec, plan_flight
from .labels import CATEGORIES, LABELS, QUERIES
from .presets import Preset
from .preview import contact_sheet, overlay, overview
from .reconstruct import ReconstructionSpec, perturb_pose, reconstruct
from .scene import generate_scene
from .sensor import SensorSpec, apply_sensor, exposure_gains, focus_blur, focus_blurs, to_uint8
from .world import V1, WorldSpec, world_streams

BACKGROUND = (0.45, 0.43, 0.38)  # beyond the town: bare land, not a black void
# A town seed S draws from the first four children of SeedSequence(S) (flight, sensor,
# reconstruction, pose); a flight seed M from the fifth child of SeedSequence(M), so that flight
# M shares no stream with the town or the default flight of any seed.
FLIGHT_SEED_CHILD = 4
# Where the town lies on the Earth (map/georef.json; sim/README.md): its world frame is ENU metres
# (layout.py), its centre at PX4's simulator home near Zurich, the ground on the WGS-84 ellipsoid's
# 488 m, so that answers come out in latitude, longitude and an RFC 7946 height.
TOWN_GEOREF = Georeference(
    47.397742, 8.545594, 488.0, height_ref="ellipsoid", source="olsplat sim make: the town centre at PX4's SITL home"
)


@dataclass(frozen=True)
class MakeOptions:
    world: WorldSpec = V1  # the evaluation world, its camera (``world.sensor``) included
    reconstruction: ReconstructionSpec = field(default_factory=ReconstructionSpec)
    jpeg_quality: int = 92
    rate_hz: float = 1.0  # frame rate of the flight
    fov_deg: float = 50.0  # horizontal field of view

    @property
    def sensor(self) -> SensorSpec:
        return self.world.sensor


def _render_frame(gaussians, frame: FlightFrame, velocity: np.ndarray, sensor: SensorSpec):
    """(rgb [H, W, 3] float, RenderResult at the frame's pose) with optional motion blur."""
    result = rasterize(gaussians, frame.camera, background=BACKGROUND)
    if sensor.blur_exposure_s <= 0:
        return result.rgb, result
    rgb = np.zeros_like(result.rgb)
    for t in np.linspace(-0.5, 0.5, sensor.blur_samples) * sensor.blur_exposure_s:
        pose = frame.camera.world_from_camera.copy()
        pose[:3, 3] += velocity * t
        moved = Camera(frame.camera.name, frame.camera.width, frame.camera.height, frame.camera.K, pose)
        rgb += rasterize(gaussians, moved, want_topk=False, background=BACKGROUND).rgb
    return rgb / sensor.blur_samples, result


def _streams(seed: int, flight_seed: int | None) -> tuple[np.random.Generator, ...]:
    """(flight, sensor, reconstruction, pose) generators. The reconstruction's (the map's) is the
    seed's whatever the flight seed; a flight seed replaces the other three with its own."""
    flight_rng, sensor_rng, recon_rng, pose_rng = [
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    ]
    if flight_seed is not None:
        flight = np.random.SeedSequence(flight_seed, spawn_key=(FLIGHT_SEED_CHILD,))
        flight_rng, sensor_rng, pose_rng = [np.random.default_rng(s) for s in flight.spawn(3)]
    return flight_rng, sensor_rng, recon_rng, pose_rng


def _flight_spec(preset: Preset, options: MakeOptions, flight_seed: int | None, rng) -> FlightSpec:
    """The flight of the preset; with a flight seed, turned by an angle drawn from ``rng`` (uniform
    in [0, 360) degrees: other view positions and image orientations, not only other noise) and
    with frames named ``flight<M>_frame_NNNN.jpg``, so that no two flights of a town share a name."""
    turn_deg, prefix = (0.0, "") if flight_seed is None else (float(rng.uniform(0.0, 360.0)), f"flight{flight_seed}_")
    return FlightSpec(
        preset.n_views,
        preset.width,
        preset.height,
        fov_deg=options.fov_deg,
        altitude_m=preset.altitude_m,
        rate_hz=options.rate_hz,
        turn_deg=turn_deg,
        name_prefix=prefix,
    )


def _town_flight_map(preset: Preset, seed: int, options: MakeOptions, flight_seed: int | None = None):
    """(true scene, flight spec, flight frames, reconstructed map, (sensor rng, pose rng, world
    flight rng)) of (preset, seed, flight seed): each part drawn from its own stream, so any part
    can be made alone. The true scene carries the world's view-dependent appearance; the map is
    made from it as in v1 (its colour from the truth's DC term, its own degree-1 residue)."""
    flight_rng, sensor_rng, recon_rng, pose_rng = _streams(seed, flight_seed)
    town_world_rng, flight_world_rng = world_streams(seed, flight_seed)
    truth = generate_scene(preset.n_gaussians, preset.size_m, seed, options.world.geometry)
    truth = with_view_dependence(truth, options.world.appearance, town_world_rng)
    spec = _flight_spec(preset, options, flight_seed, flight_rng)
    frames = plan_flight(preset.size_m, spec, flight_rng, options.world.flight, flight_world_rng)
    recon = reconstruct(truth, options.reconstruction, recon_rng)
    return truth, spec, frames, recon, (sensor_rng, pose_rng, flight_world_rng)


def _atmosphere(rgb: np.ndarray, result, frame: FlightFrame, world: WorldSpec, clouds: CloudField | None):
    """[H, W, 3] rendered rgb -> the same under the world's cloud shadows and haze (no-op in v1)."""
    if clouds is None and world.haze.beta <= 0:
        return rgb
    points, depth = surface_points(frame.camera, result.depth, result.alpha)
    if clouds is not None:
        t_s = (frame.stamp_ns - EPOCH_NS) / 1e9
        rgb = rgb * shadow_light(clouds, points, sun_vector(world.appearance), t_s)[..., None]
    if world.haze.beta > 0:
        rgb = apply_haze(rgb, depth, world.haze)
    return rgb


def prior_map(
    preset: Preset, seed: int, options: MakeOptions = MakeOptions(), flight_seed: int | None = None
) -> tuple[Gaussians, np.ndarray]:
    """The map ``make_dataset`` writes to map/point_cloud.ply for (preset, seed) (the same for every
    flight seed) and the flight's true camera centres [V, 3] (metres), without rendering a frame."""
    _, _, frames, recon, _ = _town_flight_map(preset, seed, options, flight_seed)
    return recon.gaussians, np.array([f.camera.center for f in frames])


def make_dataset(
    preset: Preset,
    seed: int,
    out: Path,
    options: MakeOptions = MakeOptions(),
    log=print,
    flight_seed: int | None = None,
    bag: Literal["mcap", "sqlite3"] | None = None,
    changes: ChangeSpec | None = None,
) -> dict:
    """Write the dataset of ``preset`` and ``seed`` to ``out``; returns the scene.json summary.

    ``flight_seed`` (>= 0): the same town and map, flown on another path (turned, other pose and
    sensor noise, frames ``flight<M>_frame_NNNN.jpg``); None: the seed's own flight. ``bag``: also
    write replay.mcap's frames (its JPEG bytes, stamps, names, cameras) to the rosbag2 folder
    replay_bag/ in that storage. ``changes`` (needs a flight seed): the flight sees the town after
    these changes (changes.py); the map stays the unchanged town's, truth/changes/ says what changed."""
    if changes is not None and flight_seed is None:
        raise ValueError("changes need a flight seed: they happen between two flights")
    start = time.perf_counter()
    truth, spec, frames, recon, (sensor_rng, pose_rng, world_rng) = _town_flight_map(preset, seed, options, flight_seed)
    before, changed = truth, None
    if changes is not None and flight_seed is not None:  # the flight sees the changed town, the map is the old one
        changed = apply_changes(truth, changes, changes_rng(flight_seed))  # before any file: a bad spec leaves none
        truth = changed.truth
    for sub in ("map", "sparse/0", "images", "annotations", "truth/true_poses", "preview"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    change_folder = out / "truth" / "changes"
    if changed is not None and changes is not None:
        map_change = mark_map(changed, before.layout, recon.gaussians.means, recon.instance, recon.category)
        write_changes(change_folder, changes, changed.records, map_change)
        log(f"changes: {len(changed.records)} ({int((map_change >= 0).sum()):,} map Gaussians) -> {change_folder}")
    log(f"scene: {len(truth.gaussians):,} Gaussians, {len(truth.layout.buildings)} buildings, "
        f"{len(truth.layout.trees)} trees, {len(truth.layout.cars)} cars on {preset.size_m:.0f} m x "
        f"{preset.size_m:.0f} m")  # fmt: skip
    gains = exposure_gains(len(frames), options.sensor, sensor_rng)
    blurs = focus_blurs(len(frames), options.sensor, sensor_rng)
    world = options.world
    clouds = CloudField(world.clouds, world_rng) if world.clouds.coverage > 0 else None
    sfm_cameras = [perturb_pose(f.camera, options.reconstruction, pose_rng) for f in frames]

    write_ply(out / "map" / "point_cloud.ply", recon.gaussians)
    write_georef(out / "map", TOWN_GEOREF)
    write_colmap(out / "sparse" / "0", sfm_cameras, binary=False)
    write_colmap(out / "truth" / "true_poses", [f.camera for f in frames], binary=False)
    write_ply(out / "truth" / "ground_truth.ply", truth.gaussians)
    np.savez_compressed(
        out / "truth" / "map_labels.npz", category=recon.category, instance=recon.instance, label=recon.label
    )
    np.savez_compressed(
        out / "truth" / "ground_truth_labels.npz", category=truth.category, instance=truth.instance, label=truth.label
    )
    (out / "truth" / "labels.json").write_text(json.dumps({"categories": CATEGORIES, "labels": LABELS}, indent=2))
    log(f"map: {len(recon.gaussians):,} Gaussians -> {out / 'map' / 'point_cloud.ply'}")

    seen: dict[int, set[int]] = {i: set() for i in range(len(LABELS))}
    previews = []
    preview_at = set(np.linspace(0, len(frames) - 1, min(6, len(frames))).round().astype(int).tolist())

    def rendered():
        for i, frame in enumerate(frames):
            a, b = frames[max(i - 1, 0)], frames[min(i + 1, len(frames) - 1)]  # central difference
            velocity = (b.camera.center - a.camera.center) / max((b.stamp_ns - a.stamp_ns) / 1e9, 1e-9)
            rgb, result = _render_frame(truth.gaussians, frame, velocity, options.sensor)
            rgb = focus_blur(_atmosphere(rgb, result, frame, world, clouds), blurs[i])
            image = to_uint8(apply_sensor(rgb, gains[i], options.sensor, sensor_rng))
            jpeg = encode_jpeg(image, options.jpeg_quality)
            (out / "images" / frame.camera.name).write_bytes(jpeg)
            labels, instances = label_maps(
                result.topk_ids, result.topk_weights, result.alpha, truth.label, truth.instance
            )
            doc = annotate_view(labels, instances, f"../images/{frame.camera.name}")
            if changed is not None:
                old = rasterize(before.gaussians, frame.camera, background=BACKGROUND).topk_ids
                mask = change_mask(old, result.topk_ids, changed.before_ids, changed.after_ids)
                write_mask(change_folder, Path(frame.camera.name).stem, mask)
            (out / "annotations" / (Path(frame.camera.name).stem + ".json")).write_text(json.dumps(doc))
            for shape in doc["shapes"]:
                if shape["group_id"] is not None:
                    seen[LABELS.index(shape["label"])].add(shape["group_id"])
            if i in preview_at:
                decoded = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
                assert decoded is not None  # we encoded it just above
                previews.append((f"{frame.camera.name} ({frame.kind})", decoded, overlay(decoded[..., ::-1], doc)))
            if (i + 1) % max(1, len(frames) // 10) == 0 or i + 1 == len(frames):
                log(f"frames: {i + 1}/{len(frames)} ({time.perf_counter() - start:.0f} s)")
            yield SourceFrame(i, frame.stamp_ns, frame.camera.name, image, sfm_cameras[i], jpeg)

    write_mcap(out / "replay.mcap", rendered())
    if bag is not None:
        write_rosbag2(out / "replay_bag", read_replay(out / "replay.mcap"), bag)
    write_timestamps(out / "images" / "timestamps.csv", [f.camera.name for f in frames], [f.stamp_ns for f in frames])

    queries = []
    for text, labels, instance_query in QUERIES:
        ids = sorted(set().union(*(seen[LABELS.index(label)] for label in labels))) if instance_query else []
        queries.append({"text": text, "labels": list(labels), "instances": ids})
    (out / "queries.json").write_text(json.dumps({"labels": LABELS, "queries": queries}, indent=2))

    cv2.imwrite(str(out / "preview" / "contact_sheet.jpg"), contact_sheet(previews), [cv2.IMWRITE_JPEG_QUALITY, 90])
    kinds = [(f.kind, f.camera) for f in frames]
    cv2.imwrite(
        str(out / "preview" / "overview.jpg"),
        overview(truth.gaussians, preset.size_m, kinds, background=BACKGROUND),
        [cv2.IMWRITE_JPEG_QUALITY, 90],
    )

    summary = {
        "preset": asdict(preset),
        "seed": seed,
        "flight_seed": flight_seed,  # null: the seed's own flight
        "flight_turn_deg": spec.turn_deg,
        "ground_truth_gaussians": len(truth.gaussians),
        "map_gaussians": len(recon.gaussians),
        "views": len(frames),
        "buildings": len(truth.layout.buildings),
        "trees": len(truth.layout.trees),
        "cars": len(truth.layout.cars),
        "options": asdict(options),
    }
    if changed is not None and changes is not None:  # the key only with changes: other scene.json stay as they were
        summary["changes"] = change_summary(changes, changed.records)
    (out / "scene.json").write_text(json.dumps(summary, indent=2))
    log(f"done in {time.perf_counter() - start:.0f} s -> {out}")
    return summary
