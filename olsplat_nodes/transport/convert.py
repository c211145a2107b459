"""Messages <-> core values, for every node: the one place where wire fields meet the core's
types. Each ``*_of`` function checks a decoded message against itself and raises ValueError
naming the inconsistency (the node counts and drops the message); each ``*_message`` function
builds a wire message from core values."""

from __future__ import annotations

import time

import numpy as np

from olsplat_msgs import (
    ImageFrame,
    Instance,
    Instance2D,
    Instance3D,
    QueryReply,
    QueryRequest,
    RegionFeatures,
    ViewPose,
)

from ..scene import Camera


def camera_of(message: ImageFrame | RegionFeatures) -> Camera:
    """The ``scene.Camera`` of an ImageFrame / RegionFeatures; ValueError when its fields are
    inconsistent (the photo's size against the camera's)."""
    K, pose, dist = (_array(message, name) for name in ("K", "world_from_camera", "D"))
    camera = Camera(message.name, message.width, message.height, K, pose, dist)
    if message.image is not None and message.image.shape != (message.height, message.width, 3):
        raise ValueError(f"image is {message.image.shape}, but the camera says {message.height}x{message.width}x3")
    return camera


def _array(message: ImageFrame | RegionFeatures, name: str) -> np.ndarray:
    """A required array field of a message; ValueError when it is absent (a decoded message
    always has it: the codec checks; a message built in code might not)."""
    value = getattr(message, name)
    if value is None:
        raise ValueError(f"{type(message).__name__}.{name} is missing")
    return value


def frame_message(frame, seq: int, stamp_ns: int | None = None) -> ImageFrame:
    """A source frame (``sources.SourceFrame``) as the wire message, stamped ``stamp_ns``
    (default: now)."""
    camera = frame.camera
    return ImageFrame(
        stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns,
        seq=seq,
        frame_id="camera",
        name=frame.name,
        image=np.ascontiguousarray(frame.image, np.uint8),
        K=camera.K,
        D=camera.dist,
        distortion_model="plumb_bob" if len(camera.dist) else "none",
        world_from_camera=camera.world_from_camera,
        width=camera.width,
        height=camera.height,
    )


def regions_message(frame: ImageFrame, label_maps: np.ndarray, bank: list[np.ndarray], encoder: str) -> RegionFeatures:
    """The wire message of one frame's regions: ``label_maps`` [L, H, W] (-1 = no region) and
    the feature bank, one [R_l, D] array per level, sent as one float16 [sum R_l, D] array."""
    return RegionFeatures(
        stamp_ns=frame.stamp_ns,
        seq=frame.seq,
        frame_id=frame.frame_id,
        name=frame.name,
        source_seq=frame.seq,
        encoder=encoder,
        label_maps=label_maps.astype(np.int32),
        level_sizes=np.array([len(f) for f in bank], np.int32),
        features=np.concatenate(bank).astype(np.float16),
        image=frame.image,
        K=frame.K,
        D=frame.D,
        distortion_model=frame.distortion_model,
        world_from_camera=frame.world_from_camera,
        width=frame.width,
        height=frame.height,
    )


def view_of(
    message: RegionFeatures, encoder: str | None, feature_dim: int | None, level_weights
) -> tuple[Camera, np.ndarray, list[np.ndarray], np.ndarray]:
    """(camera, label maps [L, H, W], feature bank per level, photo [H, W, 3]) of a view to store,
    checked against itself and against the run: the run's ``encoder`` and ``feature_dim`` (None:
    the first view sets them) and one level weight per level when ``level_weights`` is given.
    ValueError naming the problem otherwise: the accumulator drops such a view and counts it."""
    if encoder is not None and message.encoder != encoder:
        raise ValueError(f"encoder {message.encoder!r}, but this run's store holds {encoder!r} features")
    camera = camera_of(message)
    label_maps, bank = split_bank(message)
    dim = bank[0].shape[1]
    if feature_dim is not None and dim != feature_dim:  # one such view would stop every later refinement
        raise ValueError(f"features of width {dim}, but this run's store holds width {feature_dim}")
    image = split_image(message)
    if level_weights is not None and len(level_weights) != len(label_maps):
        raise ValueError(
            f"{len(label_maps)} region levels, but level_weights has {len(level_weights)} weights "
            "(set region_encoder.level_counts to as many levels)"
        )
    return camera, label_maps, bank, image


def split_image(message: RegionFeatures) -> np.ndarray:
    """The view's photo [H, W, 3] uint8 RGB that travels with its regions (checked by ``camera_of``)."""
    return _array(message, "image")


def split_bank(message: RegionFeatures) -> tuple[np.ndarray, list[np.ndarray]]:
    """(label maps [L, H, W] int32, bank per level [R_l, D] float32) of a RegionFeatures;
    ValueError naming the inconsistency when the message does not describe itself correctly."""
    labels, sizes, features = (_array(message, name) for name in ("label_maps", "level_sizes", "features"))
    if labels.ndim != 3 or not len(labels) or labels.shape[1:] != (message.height, message.width):
        raise ValueError(f"label maps are {labels.shape}, the image is {message.height}x{message.width}")
    if len(sizes) != len(labels) or (sizes < 0).any() or int(sizes.sum()) != len(features):
        raise ValueError(
            f"level sizes {sizes.tolist()} do not match {len(labels)} levels and {len(features)} feature rows"
        )
    if not np.isfinite(features).all():
        raise ValueError("the feature bank holds NaN or infinite values")
    offsets = np.cumsum([0, *sizes.tolist()])
    for level, (label_map, size) in enumerate(zip(labels, sizes, strict=True)):
        if label_map.min() < -1 or label_map.max() >= size:
            raise ValueError(
                f"level {level}: labels span {label_map.min()}..{label_map.max()}, the level has {size} regions"
            )
    return labels, [np.asarray(features[offsets[i] : offsets[i + 1]], np.float32) for i in range(len(sizes))]


def reply_for(
    answer,
    request: QueryRequest,
    map_version: int,
    image: np.ndarray | None,
    seconds: float,
    georef=None,
) -> QueryReply:
    """The wire answer of a core ``query.QueryAnswer``: 3D instances, then the 2D regions in the view, as
    ``Instance`` records (``msgs/schema.yaml``; ``encode`` checks them). With ``georef`` (the map's
    ``scene.geodesy.Georeference``) the 3D instances carry latitude, longitude and altitudes, else NaN."""
    from ..query.geojson import locate

    instances: list[Instance] = [
        Instance3D(
            id=i,
            kind="3d",
            n_gaussians=int(inst.gaussians),
            centroid=[float(x) for x in inst.centre],  # world metres
            box_min=[float(x) for x in inst.box_min],
            box_max=[float(x) for x in inst.box_max],
            latitude=inst.latitude,
            longitude=inst.longitude,
            altitude=inst.altitude,
            footprint=[float(v) for corner in inst.footprint for v in corner],  # [lon, lat] x 4
            box_altitude=[float(v) for v in inst.box_altitude],
        )
        for i, inst in enumerate(locate(answer.instances, georef))
    ]
    instances += [
        Instance2D(
            id=i,
            kind="2d",
            box2d=[int(x) for x in r.box],  # x0, y0, x1, y1, end exclusive
            centre_px=[float(x) for x in r.centre],  # top-left pixel's centre at (0.5, 0.5)
            area_px=int(r.pixels),
        )
        for i, r in enumerate(answer.regions)
    ]
    return QueryReply(
        stamp_ns=time.time_ns(),
        frame_id="map",
        request_id=request.request_id,
        status="ok",
        message=f"{answer.chosen_count} Gaussians pick it over {len(answer.negatives)} negatives "
        f"({', '.join(answer.negatives)})"
        + (f"; words the encoder does not know: {', '.join(answer.unknown_words)}" if answer.unknown_words else ""),
        text=answer.text,
        view=request.view,
        map_version=map_version,
        height_ref="" if georef is None else georef.height_ref,
        instances=instances,
        heatmap=None if answer.heatmap is None else answer.heatmap.astype(np.float32),
        mask=None if answer.mask is None else answer.mask.astype(np.uint8),
        image=image,
        seconds=seconds,
    )


def view_pose(camera: Camera) -> ViewPose:
    """The ``ViewPose`` record of a view's camera (row-major K and pose)."""
    return ViewPose(
        name=camera.name,
        width=int(camera.width),
        height=int(camera.height),
        K=[float(x) for x in camera.K.reshape(-1)],
        world_from_camera=[float(x) for x in camera.world_from_camera.reshape(-1)],
    )


def camera_of_pose(record: ViewPose) -> Camera:
    """The ``scene.Camera`` of a ``ViewPose`` record; ValueError when it is not a camera."""
    K, pose = np.asarray(record["K"], np.float64), np.asarray(record["world_from_camera"], np.float64)
    return Camera(record["name"], record["width"], record["height"], K, pose)
