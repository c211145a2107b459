"""The messages of the node graph as dataclasses, one per entry of ``schema.yaml``.

Written by hand for readable code and editor help; ``check_against_schema`` (run at import and
by tests/msgs) fails when a name, order, type or default differs from ``schema.yaml``, so the two
cannot drift. Field descriptions live in the schema (and the README tables generated from it);
the comments here give shapes and units.

Every message starts with ``stamp_ns`` (ns since the Unix epoch), ``seq`` (+1 per message of a
stream, set by the sender) and ``frame_id`` (stream name). Array fields are ``np.ndarray | None``
and default to ``None`` (a dataclass needs defaults after the defaulted common fields); a
required array left ``None`` is refused by ``encode`` (the schema, and the README, say which
arrays are optional). Arrays from ``decode`` are read-only views of the received buffers: copy
before modifying.

Records (maps inside a field, ``records:`` in the schema) are ``TypedDict`` classes: plain dicts
at run time (JSON-ready, indexable as before), typed for editors and mypy, one class per kind of
a tagged record (``Instance3D``, ``Instance2D``: ``Instance`` is their union), checked against
the schema by ``check_against_schema`` like the messages.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, Literal, TypedDict, get_type_hints

import numpy as np

from .schema import fixed_list, load_schema


class Instance3D(TypedDict):
    """Record ``Instance`` of kind "3d": a cluster of the Gaussians that pick the query."""

    id: int  # 0, 1, ... by decreasing n_gaussians
    kind: Literal["3d"]
    n_gaussians: int
    centroid: list[float]  # [x, y, z] world metres
    box_min: list[float]  # [x, y, z] world metres
    box_max: list[float]  # [x, y, z] world metres
    latitude: float  # WGS-84 degrees of the centroid; NaN: the map has no georeference
    longitude: float  # WGS-84 degrees
    altitude: float  # metres above QueryReply.height_ref
    footprint: list[float]  # 8: [lon, lat] x 4 lower box corners, counter-clockwise, degrees
    box_altitude: list[float]  # [lowest, highest] metres above QueryReply.height_ref


class Instance2D(TypedDict):
    """Record ``Instance`` of kind "2d": a connected region of the mask in the requested view."""

    id: int  # 0, 1, ... by decreasing area_px
    kind: Literal["2d"]
    box2d: list[int]  # [x0, y0, x1, y1] pixels, end exclusive
    centre_px: list[float]  # [x, y] pixels, top-left pixel's centre at (0.5, 0.5)
    area_px: int


Instance = Instance3D | Instance2D


class ViewPose(TypedDict):
    """Record ``ViewPose``: one aggregated view's camera."""

    name: str
    width: int  # pixels
    height: int  # pixels
    K: list[float]  # 9: row-major 3x3 intrinsics, pixels
    world_from_camera: list[float]  # 16: row-major 4x4 pose, OpenCV axes, world metres


@dataclass
class ImageFrame:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    name: str = ""
    image: np.ndarray | None = None  # [H, W, 3] uint8 RGB
    K: np.ndarray | None = None  # [3, 3] float64, pixels
    D: np.ndarray | None = None  # [n] float64, may be empty
    distortion_model: str = "none"  # "plumb_bob" | "none"
    world_from_camera: np.ndarray | None = None  # [4, 4] float64, OpenCV axes, metres
    width: int = 0
    height: int = 0


@dataclass
class EndOfStream:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    source: str = ""
    frames: int = 0
    names: list[str] = field(default_factory=list)


@dataclass
class RegionFeatures:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    name: str = ""
    source_seq: int = 0
    encoder: str = ""
    label_maps: np.ndarray | None = None  # [L, H, W] int32, -1 = no region
    level_sizes: np.ndarray | None = None  # [L] int32
    features: np.ndarray | None = None  # [R, D] float16 | float32, R = level_sizes.sum()
    image: np.ndarray | None = None  # [H, W, 3] uint8 RGB
    K: np.ndarray | None = None  # [3, 3] float64
    D: np.ndarray | None = None  # [n] float64
    distortion_model: str = "none"
    world_from_camera: np.ndarray | None = None  # [4, 4] float64
    width: int = 0
    height: int = 0


@dataclass
class ObservationsAdded:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    name: str = ""
    source_seq: int = 0
    observations: int = 0
    gaussians: int = 0
    views_in_store: int = 0
    duplicate: bool = False


@dataclass
class MapUpdated:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    version: int = 0
    path: str = ""
    views: int = 0
    observed_gaussians: int = 0
    encoder: str = ""
    final: bool = False


@dataclass
class QueryRequest:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""
    text: str = ""
    view: str = ""  # "" = 3D only
    heatmap: bool = True
    threshold: float = math.nan  # NaN = the server's default rule
    negatives: list[str] = field(default_factory=list)
    splats: int = 0  # 0 = no splat_margin; else the max_splats of the client's SplatsReply
    since: str = ""  # a change query's earlier flight ("f0"); "" = an ordinary query
    gone: bool = False  # with since and a text: what moved away from it
    preview: bool = False  # a quick first answer on a view: <= 320 px, no 3D instances


@dataclass
class QueryReply:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""
    status: str = "ok"  # "ok" | "no_map" | "bad_request" | "error"
    message: str = ""
    text: str = ""
    view: str = ""
    map_version: int = 0
    height_ref: str = ""  # "ellipsoid" | "msl" | "" (no georeference: the instances' geodetic fields are NaN)
    instances: list[Instance] = field(default_factory=list)
    heatmap: np.ndarray | None = None  # [H, W] float32 in [0, 1]
    mask: np.ndarray | None = None  # [H, W] uint8, 0 | 1
    image: np.ndarray | None = None  # [H, W, 3] uint8 RGB overlay
    splat_margin: np.ndarray | None = None  # [M] float16 per browser splat; NaN = never observed
    since: str = ""  # a change query's earlier flight; "" = an ordinary query
    now: str = ""  # a change query's later flight
    change_scores: np.ndarray | None = None  # [K] float32 median change score per 3D instance
    seconds: float = 0.0
    preview: bool = False  # a preview's reply (request.preview): no 3D instances


@dataclass
class SplatsRequest:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""
    max_splats: int = 300000


@dataclass
class SplatsReply:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""
    status: str = "ok"  # "ok" | "bad_request" | "busy" | "error"
    message: str = ""
    total: int = 0  # Gaussians in the prior map
    centers: np.ndarray | None = None  # [M, 3] float32 world metres
    covariances: np.ndarray | None = None  # [M, 6] float32 upper triangle, m^2
    rgbs: np.ndarray | None = None  # [M, 3] uint8
    opacities: np.ndarray | None = None  # [M] uint8, 255 = 1


@dataclass
class ViewsRequest:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""
    start: int = 0


@dataclass
class ViewsReply:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""
    start: int = 0
    total: int = 0
    views: list[ViewPose] = field(default_factory=list)


@dataclass
class StatusRequest:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""


@dataclass
class StatusReply:
    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    request_id: str = ""
    nodes: list[dict] = field(default_factory=list)
    map_version: int = 0


@dataclass
class DiagnosticStatus:
    OK: ClassVar[int] = 0
    WARN: ClassVar[int] = 1
    ERROR: ClassVar[int] = 2
    STALE: ClassVar[int] = 3

    stamp_ns: int = 0
    seq: int = 0
    frame_id: str = ""
    node: str = ""
    level: int = 0
    message: str = ""
    values: dict = field(default_factory=dict)  # str -> int | float | str


MESSAGE_CLASSES = (
    ImageFrame,
    EndOfStream,
    RegionFeatures,
    ObservationsAdded,
    MapUpdated,
    QueryRequest,
    QueryReply,
    SplatsRequest,
    SplatsReply,
    ViewsRequest,
    ViewsReply,
    StatusRequest,
    StatusReply,
    DiagnosticStatus,
)
MESSAGES: dict[str, type] = {f"olsplat_msgs/{cls.__name__}": cls for cls in MESSAGE_CLASSES}
# record name -> {kind: TypedDict class} (a record without a tag: {None: class})
RECORDS: dict[str, dict[str | None, Any]] = {
    "Instance": {"3d": Instance3D, "2d": Instance2D},
    "ViewPose": {None: ViewPose},
}

_ANNOTATIONS = {
    "str": "str",
    "int": "int",
    "float": "float",
    "bool": "bool",
    "list[str]": "list[str]",
    "list[dict]": "list[dict]",
    "dict": "dict",
}


def _same_default(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


_RECORD_HINTS: dict[str, object] = {"str": str, "int": int, "float": float, "bool": bool}
_LIST_HINTS: dict[str, object] = {"int": list[int], "float": list[float]}


def _record_hint(spec, kind: str | None, tag: str | None) -> object:
    """The annotation a record field of ``spec`` has in the TypedDict of ``kind``."""
    if spec.name == tag:
        return Literal[kind]
    fixed = fixed_list(spec.type)
    return _LIST_HINTS[fixed[0]] if fixed is not None else _RECORD_HINTS[spec.type]


def _check_records(schema) -> list[str]:
    problems = []
    if list(RECORDS) != list(schema.records):
        problems.append(f"records differ: classes {list(RECORDS)}, schema {list(schema.records)}")
    for name, classes in RECORDS.items():
        record = schema.records.get(name)
        if record is None:
            continue
        kinds = list(record.kinds) or [None]
        if list(classes) != kinds:
            problems.append(f"record {name}: classes for kinds {list(classes)}, schema has {kinds}")
            continue
        for kind, cls in classes.items():
            specs = record.fields_of(kind)
            hints = get_type_hints(cls)
            want = {s.name: _record_hint(s, kind, record.tag) for s in specs}
            if list(hints) != list(want) or hints != want:
                problems.append(f"{cls.__name__}: keys and types {hints}, schema says {want}")
            if cls.__required_keys__ != frozenset(want):
                problems.append(f"{cls.__name__}: every key must be required (record fields are never optional)")
    return problems


def check_against_schema() -> list[str]:
    """Every difference between these classes and ``schema.yaml`` (empty when they agree):
    message set, field names and order, annotations, defaults; record TypedDicts: kinds, keys
    and their order, types."""
    schema = load_schema()
    problems = _check_records(schema)
    if list(MESSAGES) != [m.schema_name for m in schema.messages.values()]:
        problems.append(
            f"messages differ: classes {list(MESSAGES)}, schema {[m.schema_name for m in schema.messages.values()]}"
        )
    for cls in MESSAGE_CLASSES:
        spec = schema.messages.get(cls.__name__)
        if spec is None:
            continue
        specs = [*schema.common, *spec.fields]
        got = fields(cls)
        if [f.name for f in got] != [s.name for s in specs]:
            problems.append(f"{cls.__name__}: fields {[f.name for f in got]} != schema {[s.name for s in specs]}")
            continue
        for f, s in zip(got, specs, strict=True):
            if s.is_array:
                want_type = "np.ndarray | None"  # required or not: None until set (encode refuses a required None)
                want_default = None
            elif s.record is not None:
                want_type, want_default = s.type, []
            else:
                want_type = _ANNOTATIONS[s.type] + (" | None" if s.optional else "")
                want_default = {"list[str]": [], "list[dict]": [], "dict": {}}.get(s.type, s.default)
            default = f.default_factory() if f.default_factory is not MISSING else f.default
            if f.type != want_type:
                problems.append(f"{cls.__name__}.{f.name}: annotation {f.type!r}, schema wants {want_type!r}")
            if not _same_default(default, want_default):
                problems.append(f"{cls.__name__}.{f.name}: default {default!r}, schema says {want_default!r}")
    return problems


_problems = check_against_schema()
if _problems:  # a broken schema must stop the process, not produce silently wrong bytes
    raise ImportError("olsplat_msgs classes disagree with schema.yaml: " + "; ".join(_problems))
