"""One or more filled-in instances of every message, covering None arrays, empty arrays, every
allowed dtype of a field, NaN, nested dicts, records of every kind and unicode; shared by the
codec tests."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from olsplat_msgs import (
    DiagnosticStatus,
    EndOfStream,
    ImageFrame,
    Instance2D,
    Instance3D,
    MapUpdated,
    ObservationsAdded,
    QueryReply,
    QueryRequest,
    RegionFeatures,
    SplatsReply,
    SplatsRequest,
    StatusReply,
    StatusRequest,
    ViewPose,
    ViewsReply,
    ViewsRequest,
)


def _camera(rng: np.random.Generator, h: int, w: int) -> dict:
    return {
        "image": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        "K": np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]]),
        "D": rng.normal(size=5),
        "distortion_model": "plumb_bob",
        "world_from_camera": np.eye(4),
        "width": w,
        "height": h,
    }


def sample_messages() -> list[tuple[str, object]]:
    """(id, message) pairs: at least one per message class."""
    rng = np.random.default_rng(7)
    stamp = 1_700_000_000_123_456_789
    levels = np.array([3, 5], dtype=np.int32)
    label_maps = rng.integers(-1, 3, (2, 6, 8), dtype=np.int32)
    out = [
        ("image", ImageFrame(stamp_ns=stamp, seq=12, frame_id="uav1/cam0", name="v000.png", **_camera(rng, 6, 8))),
        (
            "image-empty-D-no-distortion",
            ImageFrame(name="ü-ñame", **{**_camera(rng, 1, 1), "D": np.zeros(0), "distortion_model": "none"}),
        ),
        ("image-zero-size", ImageFrame(**{**_camera(rng, 0, 0), "D": np.zeros(0)})),
        ("eos", EndOfStream(seq=3, source="replay", frames=2, names=["a", "b"])),
        ("eos-empty", EndOfStream()),
        (
            "regions-f16",
            RegionFeatures(
                seq=1,
                name="v000",
                source_seq=12,
                encoder="olsplat-cnn64:x",
                label_maps=label_maps,
                level_sizes=levels,
                features=rng.normal(size=(8, 16)).astype(np.float16),
                **_camera(rng, 6, 8),
            ),
        ),
        (
            "regions-f32-empty",
            RegionFeatures(
                label_maps=np.zeros((0, 6, 8), np.int32),
                level_sizes=np.zeros(0, np.int32),
                features=np.zeros((0, 512), np.float32),
                **_camera(rng, 6, 8),
            ),
        ),
        (
            "observations",
            ObservationsAdded(
                seq=9, name="v000", source_seq=1, observations=123456, gaussians=999, views_in_store=4, duplicate=True
            ),
        ),
        (
            "map",
            MapUpdated(
                version=5, path="/run/map/v5.npz", views=4, observed_gaussians=12_000_000, encoder="e", final=True
            ),
        ),
        (
            "query",
            QueryRequest(
                request_id="r1",
                text="red roof buildings",
                view="v000",
                heatmap=False,
                threshold=0.4,
                negatives=["road", "tree"],
            ),
        ),
        ("query-nan", QueryRequest(request_id="r2", text="road")),
        (
            "reply-full",
            QueryReply(
                request_id="r1",
                status="ok",
                text="road",
                view="v000",
                map_version=5,
                height_ref="ellipsoid",
                instances=[
                    Instance3D(
                        id=0,
                        kind="3d",
                        n_gaussians=10,
                        centroid=[1.0, 2.0, 3.0],
                        box_min=[0.5, -1e300, 2.0],
                        box_max=[1.5, 2.5, math.inf],
                        latitude=47.397742,
                        longitude=8.545594,
                        altitude=491.5,
                        footprint=[8.5, 47.3, 8.6, 47.3, 8.6, 47.4, 8.5, 47.4],
                        box_altitude=[490.0, 493.0],
                    ),
                    Instance3D(
                        id=1,
                        kind="3d",
                        n_gaussians=2**62,
                        centroid=[0.0] * 3,
                        box_min=[0.0] * 3,
                        box_max=[0.0] * 3,
                        latitude=-90.0,
                        longitude=180.0,
                        altitude=-1e300,
                        footprint=[0.0] * 8,
                        box_altitude=[-math.inf, 1e300],
                    ),
                    Instance2D(id=0, kind="2d", box2d=[0, 1, 2, 3], centre_px=[1.0, 2.0], area_px=4),
                ],
                heatmap=rng.random((6, 8), dtype=np.float32),
                mask=(rng.random((6, 8)) > 0.5).astype(np.uint8),
                image=rng.integers(0, 256, (6, 8, 3), dtype=np.uint8),
                splat_margin=np.array([0.25, -0.5, np.nan], np.float16),
                seconds=0.125,
            ),
        ),
        ("query-splats", QueryRequest(request_id="r3", text="roof", splats=300_000)),
        ("splats-request", SplatsRequest(request_id="p1", max_splats=5)),
        (
            "splats-reply",
            SplatsReply(
                request_id="p1",
                message="3 of 9 Gaussians drawn",
                total=9,
                centers=rng.normal(size=(3, 3)).astype(np.float32),
                covariances=rng.random((3, 6), dtype=np.float32),
                rgbs=rng.integers(0, 256, (3, 3), dtype=np.uint8),
                opacities=np.array([0, 128, 255], np.uint8),
            ),
        ),
        ("splats-refused", SplatsReply(request_id="p2", status="bad_request", message="max_splats must be 1..500,000")),
        ("views-request", ViewsRequest(request_id="v1", start=500)),
        (
            "views-reply",
            ViewsReply(
                request_id="v1",
                start=500,
                total=502,
                views=[
                    ViewPose(
                        name="frame_0500.jpg",
                        width=640,
                        height=480,
                        K=[500.0, 0, 320, 0, 500, 240, 0, 0, 1],
                        world_from_camera=[float(x) for x in np.eye(4).reshape(-1)],
                    ),
                    ViewPose(name="ü", width=1, height=1, K=[1.0] * 9, world_from_camera=[0.0] * 16),
                ],
            ),
        ),
        ("views-none", ViewsReply(request_id="v2", start=7, total=3)),
        ("reply-none-arrays", QueryReply(request_id="r2", status="no_map", message="no snapshot yet")),
        (
            "reply-empty-arrays",
            QueryReply(heatmap=np.zeros((0, 0), np.float32), mask=np.zeros((0, 4), np.uint8), image=None),
        ),
        ("status-request", StatusRequest(request_id="s1")),
        (
            "status-reply",
            StatusReply(
                request_id="s1",
                map_version=2,
                nodes=[
                    {
                        "node": "ingest",
                        "level": 0,
                        "values": {"rate_hz": 2.5, "drops": 1},
                        "age_s": 0.3,
                        "nested": {"a": [1, [2, {"b": None}]]},
                    }
                ],
            ),
        ),
        (
            "diagnostics",
            DiagnosticStatus(
                stamp_ns=stamp,
                seq=2**63 - 1,
                node="accumulator",
                level=DiagnosticStatus.WARN,
                message="slow",
                values={"rate_hz": 1.5, "latency_ms": 250, "drops": 3, "state": "running", "ok": True},
            ),
        ),
    ]
    return out


def assert_same(a, b) -> None:
    """Field-by-field equality: arrays by dtype, shape and values; floats NaN-aware."""
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            assert isinstance(x, np.ndarray) and isinstance(y, np.ndarray), f.name
            assert x.dtype.newbyteorder("<") == y.dtype and x.shape == y.shape, (
                f.name,
                x.dtype,
                y.dtype,
                x.shape,
                y.shape,
            )
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), f.name  # bit-exact incl. NaN
        elif isinstance(x, float) and math.isnan(x):
            assert isinstance(y, float) and math.isnan(y), f.name
        else:
            assert x == y and type(x) is type(y), (f.name, x, y)
