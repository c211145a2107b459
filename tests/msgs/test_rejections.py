"""Every way decode refuses frames, each with its specific WireError subclass and a message that
names the field and the problem."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from olsplat_msgs import (
    ImageFrame,
    Instance2D,
    Instance3D,
    MalformedMessage,
    MessageTooLarge,
    QueryReply,
    RegionFeatures,
    StatusReply,
    StatusRequest,
    UnknownSchema,
    UnsupportedVersion,
    WireError,
    decode,
    encode,
)


def _region_frames() -> list[bytes]:
    msg = RegionFeatures(
        name="v",
        label_maps=np.zeros((2, 2, 3), np.int32),
        level_sizes=np.array([1, 1], np.int32),
        features=np.ones((2, 4), np.float16),
        image=np.zeros((2, 3, 3), np.uint8),
        K=np.eye(3),
        D=np.zeros(0),
        world_from_camera=np.eye(4),
        width=3,
        height=2,
    )
    return encode(msg, "regions")


INSTANCES = [
    Instance3D(
        id=0,
        kind="3d",
        n_gaussians=30,
        centroid=[1.0, 2.0, 3.0],
        box_min=[0.0, 1.0, 2.0],
        box_max=[2.0, 3.0, 4.0],
        latitude=47.0,
        longitude=8.0,
        altitude=403.0,
        footprint=[8.0, 47.0, 8.1, 47.0, 8.1, 47.1, 8.0, 47.1],
        box_altitude=[402.0, 404.0],
    ),
    Instance2D(id=0, kind="2d", box2d=[0, 1, 2, 3], centre_px=[1.5, 2.5], area_px=4),
]


def _reply_frames() -> list[bytes]:
    return encode(QueryReply(request_id="r", mask=np.ones((2, 2), np.uint8), instances=INSTANCES), "query")


def _with_header(frames: list[bytes], change) -> list[bytes]:
    """frames with the header unpacked, changed in place by ``change(header)``, and repacked."""
    header = msgpack.unpackb(frames[1])
    change(header)
    return [frames[0], msgpack.packb(header, use_bin_type=True), *frames[2:]]


def _set(path: str, value):
    """A header change that sets header[a][b]... (path "a.b"; list indices as ints)."""
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]

    def change(header):
        target = header
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value

    return change


def _delete(path: str):
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]

    def change(header):
        target = header
        for key in keys[:-1]:
            target = target[key]
        del target[keys[-1]]

    return change


STATUS = encode(StatusRequest(request_id="x"), "query")
REGIONS = _region_frames()
REPLY = _reply_frames()
NODES = encode(StatusReply(request_id="s", nodes=[{"node": "ingest", "level": 0}]), "query")

CASES = [
    # (id, frames, error class, words that must appear in the message)
    ("no-frames", [], MalformedMessage, "at least 2 frames"),
    ("topic-only", STATUS[:1], MalformedMessage, "at least 2 frames"),
    ("extra-frame", [*STATUS, b""], MalformedMessage, "expected 2 frames"),
    ("missing-array-frame", REGIONS[:-1], MalformedMessage, "expected 9 frames"),
    ("empty-topic", [b"", *STATUS[1:]], MalformedMessage, "topic"),
    ("topic-not-utf8", [b"\xff\xfe", *STATUS[1:]], MalformedMessage, "not UTF-8"),
    ("frame-not-bytes", [STATUS[0], 12], MalformedMessage, "frame 1"),
    ("garbage-header", [STATUS[0], b"\xc1\x00garbage"], MalformedMessage, "not a valid msgpack"),
    ("truncated-header", [STATUS[0], STATUS[1][:-3]], MalformedMessage, "not a valid msgpack"),
    ("trailing-bytes", [STATUS[0], STATUS[1] + b"\x00"], MalformedMessage, "not a valid msgpack"),
    ("header-not-map", [STATUS[0], msgpack.packb([1, 2])], MalformedMessage, "expected a msgpack map"),
    (
        "ext-type",
        [STATUS[0], msgpack.packb({"schema": msgpack.ExtType(5, b"x")})],
        MalformedMessage,
        "extension type 5",
    ),
    ("schema-missing", _with_header(STATUS, _delete("schema")), MalformedMessage, "'schema' must be a string"),
    (
        "schema-bin",
        _with_header(STATUS, _set("schema", b"olsplat_msgs/StatusRequest")),
        MalformedMessage,
        "'schema' must be a string",
    ),
    (
        "unknown-schema",
        _with_header(STATUS, _set("schema", "olsplat_msgs/Teleport")),
        UnknownSchema,
        "olsplat_msgs/Teleport",
    ),
    ("foreign-schema", _with_header(STATUS, _set("schema", "sensor_msgs/Image")), UnknownSchema, "sensor_msgs/Image"),
    ("version-6", _with_header(STATUS, _set("version", 6)), UnsupportedVersion, "version 6"),
    ("version-4", _with_header(STATUS, _set("version", 4)), UnsupportedVersion, "version 4"),
    ("version-0", _with_header(STATUS, _set("version", 0)), UnsupportedVersion, "version 0"),
    ("version-str", _with_header(STATUS, _set("version", "1")), MalformedMessage, "'version' must be an int"),
    ("version-missing", _with_header(STATUS, _delete("version")), MalformedMessage, "'version' must be an int"),
    ("header-extra-key", _with_header(STATUS, _set("comment", "hi")), MalformedMessage, "unexpected keys ['comment']"),
    ("header-missing-key", _with_header(STATUS, _delete("frame_id")), MalformedMessage, "missing keys ['frame_id']"),
    ("stamp-negative", _with_header(STATUS, _set("stamp_ns", -5)), MalformedMessage, "StatusRequest.stamp_ns"),
    ("seq-float", _with_header(STATUS, _set("seq", 1.0)), MalformedMessage, "StatusRequest.seq"),
    ("seq-bool", _with_header(STATUS, _set("seq", True)), MalformedMessage, "StatusRequest.seq"),
    ("frame-id-int", _with_header(STATUS, _set("frame_id", 3)), MalformedMessage, "StatusRequest.frame_id"),
    ("fields-not-map", _with_header(STATUS, _set("fields", [])), MalformedMessage, "'fields' must be a map"),
    (
        "field-missing",
        _with_header(STATUS, _delete("fields.request_id")),
        MalformedMessage,
        "missing fields ['request_id']",
    ),
    (
        "field-extra",
        _with_header(STATUS, _set("fields.priority", 1)),
        MalformedMessage,
        "unexpected fields ['priority']",
    ),
    (
        "field-str-is-int",
        _with_header(STATUS, _set("fields.request_id", 5)),
        MalformedMessage,
        "StatusRequest.request_id: expected str",
    ),
    (
        "field-int-is-str",
        _with_header(REGIONS, _set("fields.width", "3")),
        MalformedMessage,
        "RegionFeatures.width: expected int",
    ),
    (
        "field-int-is-bool",
        _with_header(REGIONS, _set("fields.width", True)),
        MalformedMessage,
        "RegionFeatures.width: expected int",
    ),
    (
        "field-float-is-str",
        _with_header(REPLY, _set("fields.seconds", "1")),
        MalformedMessage,
        "QueryReply.seconds: expected float",
    ),
    ("field-nil", _with_header(REPLY, _set("fields.message", None)), MalformedMessage, "QueryReply.message: None"),
    (
        "field-choice",
        _with_header(REPLY, _set("fields.status", "maybe")),
        MalformedMessage,
        "QueryReply.status: 'maybe' is not one of",
    ),
    (
        "field-list-of-int",
        _with_header(NODES, _set("fields.nodes", [1])),
        MalformedMessage,
        "StatusReply.nodes[0]: expected dict",
    ),
    (
        "field-list-is-map",
        _with_header(NODES, _set("fields.nodes", {})),
        MalformedMessage,
        "StatusReply.nodes: expected list[dict]",
    ),
    (
        "field-bin-inside",
        _with_header(NODES, _set("fields.nodes", [{"a": b"x"}])),
        MalformedMessage,
        "StatusReply.nodes[0].a",
    ),
    # records: QueryReply.instances is list[Instance] (REPLY has a 3d then a 2d instance)
    (
        "records-is-map",
        _with_header(REPLY, _set("fields.instances", {})),
        MalformedMessage,
        "QueryReply.instances: expected list[Instance] (an array of maps), got dict",
    ),
    (
        "record-is-int",
        _with_header(REPLY, _set("fields.instances", [1])),
        MalformedMessage,
        "QueryReply.instances[0]: expected a map (record Instance), got int",
    ),
    (
        "record-is-nil",
        _with_header(REPLY, _set("fields.instances.1", None)),
        MalformedMessage,
        "QueryReply.instances[1]: expected a map (record Instance), got NoneType",
    ),
    (
        "record-without-kind",
        _with_header(REPLY, _delete("fields.instances.0.kind")),
        MalformedMessage,
        "QueryReply.instances[0]: record Instance without its 'kind' key",
    ),
    (
        "record-unknown-kind",
        _with_header(REPLY, _set("fields.instances.0.kind", "4d")),
        MalformedMessage,
        "QueryReply.instances[0].kind: '4d' is not one of ['3d', '2d']",
    ),
    (
        "record-kind-not-str",
        _with_header(REPLY, _set("fields.instances.1.kind", 2)),
        MalformedMessage,
        "QueryReply.instances[1].kind: expected str, got int",
    ),
    (
        "record-missing-key",
        _with_header(REPLY, _delete("fields.instances.1.area_px")),
        MalformedMessage,
        "QueryReply.instances[1]: record Instance of kind '2d' needs exactly the keys "
        "['id', 'kind', 'box2d', 'centre_px', 'area_px']; missing ['area_px'], unexpected []",
    ),
    (
        "record-undocumented-key",  # the old description's "score", never sent
        _with_header(REPLY, _set("fields.instances.0.score", 0.9)),
        MalformedMessage,
        "missing [], unexpected ['score']",
    ),
    (
        "record-keys-of-the-other-kind",
        _with_header(REPLY, _set("fields.instances.1.kind", "3d")),
        MalformedMessage,
        "QueryReply.instances[1]: record Instance of kind '3d' needs exactly the keys",
    ),
    (
        "record-bin-key",
        _with_header(REPLY, _set("fields.instances.0", {**INSTANCES[0], b"id": 1})),
        MalformedMessage,
        "unexpected [b'id']",
    ),
    (
        "record-nil-value",
        _with_header(REPLY, _set("fields.instances.0.centroid", None)),
        MalformedMessage,
        "QueryReply.instances[0].centroid: None, but the field is not optional",
    ),
    (
        "record-short-list",
        _with_header(REPLY, _set("fields.instances.0.centroid", [1.0, 2.0])),
        MalformedMessage,
        "QueryReply.instances[0].centroid: expected float[3] (3 numbers), got list of 2 items",
    ),
    (
        "record-list-is-str",
        _with_header(REPLY, _set("fields.instances.1.box2d", "0 1 2 3")),
        MalformedMessage,
        "QueryReply.instances[1].box2d: expected int[4] (4 numbers), got str",
    ),
    (
        "record-float-in-int-list",
        _with_header(REPLY, _set("fields.instances.1.box2d.3", 3.5)),
        MalformedMessage,
        "QueryReply.instances[1].box2d[3]: expected int, got float",
    ),
    (
        "record-str-in-float-list",
        _with_header(REPLY, _set("fields.instances.1.centre_px.1", "2.5")),
        MalformedMessage,
        "QueryReply.instances[1].centre_px[1]: expected float, got str",
    ),
    (
        "record-nested-list",
        _with_header(REPLY, _set("fields.instances.0.box_max.0", [2.0])),
        MalformedMessage,
        "QueryReply.instances[0].box_max[0]: expected float, got list",
    ),
    (
        "record-bool-as-int",
        _with_header(REPLY, _set("fields.instances.1.area_px", True)),
        MalformedMessage,
        "QueryReply.instances[1].area_px: expected int, got bool",
    ),
    (
        "record-bin-value",
        _with_header(REPLY, _set("fields.instances.0.id", b"\x00")),
        MalformedMessage,
        "QueryReply.instances[0].id: expected int, got bytes",
    ),
    (
        "record-int-out-of-range",
        _with_header(REPLY, _set("fields.instances.0.n_gaussians", 2**64 - 1)),
        MalformedMessage,
        "QueryReply.instances[0].n_gaussians: 18446744073709551615 outside the signed 64-bit range",
    ),
    ("arrays-not-list", _with_header(REPLY, _set("arrays", {})), MalformedMessage, "'arrays' must list 5 entries"),
    (
        "arrays-too-few",
        _with_header(REPLY, lambda h: h["arrays"].pop()),
        MalformedMessage,
        "'arrays' must list 5 entries",
    ),
    (
        "array-entry-not-map",
        _with_header(REPLY, _set("arrays.1", "mask")),
        MalformedMessage,
        "QueryReply.mask: array entry must be a map",
    ),
    (
        "array-entry-extra-key",
        _with_header(REPLY, _set("arrays.1.order", "C")),
        MalformedMessage,
        "QueryReply.mask: array entry must be a map",
    ),
    (
        "array-order-swapped",
        _with_header(REPLY, lambda h: h["arrays"].reverse()),
        MalformedMessage,
        "QueryReply.heatmap: array entry named 'change_scores'",
    ),
    (
        "dtype-unknown",
        _with_header(REPLY, _set("arrays.1.dtype", "<c8")),
        MalformedMessage,
        "QueryReply.mask: dtype '<c8' is not a wire dtype",
    ),
    (
        "dtype-big-endian",
        _with_header(REGIONS, _set("arrays.2.dtype", ">f2")),
        MalformedMessage,
        "RegionFeatures.features: dtype '>f2' is not a wire dtype",
    ),
    (
        "dtype-object",
        _with_header(REPLY, _set("arrays.1.dtype", "|O")),
        MalformedMessage,
        "QueryReply.mask: dtype '|O'",
    ),
    (
        "dtype-not-allowed",
        _with_header(REGIONS, _set("arrays.2.dtype", "<f8")),
        MalformedMessage,
        "RegionFeatures.features: dtype '<f8' not allowed, expected float16 or float32",
    ),
    (
        "dtype-not-str",
        _with_header(REPLY, _set("arrays.1.dtype", 1)),
        MalformedMessage,
        "QueryReply.mask: dtype must be a string",
    ),
    ("rank-mismatch", _with_header(REPLY, _set("arrays.1.shape", [4])), MalformedMessage, "QueryReply.mask: rank 1"),
    (
        "fixed-dim-mismatch",
        _with_header(REGIONS, _set("arrays.4.shape", [9])),
        MalformedMessage,
        "RegionFeatures.K: rank 1",
    ),
    (
        "fixed-dim-value",
        _with_header(REGIONS, _set("arrays.4.shape", [1, 9])),
        MalformedMessage,
        "RegionFeatures.K: shape [1, 9], axis 0 must be 3",
    ),
    (
        "shape-negative",
        _with_header(REPLY, _set("arrays.1.shape", [-2, -2])),
        MalformedMessage,
        "QueryReply.mask: shape must be a list of non-negative ints",
    ),
    (
        "shape-bool",
        _with_header(REPLY, _set("arrays.1.shape", [True, 4])),
        MalformedMessage,
        "QueryReply.mask: shape must be a list",
    ),
    ("buffer-short", [*REPLY[:3], REPLY[3][:-1], *REPLY[4:]], MalformedMessage, "QueryReply.mask: frame has 3 bytes"),
    (
        "buffer-long",
        [*REPLY[:3], REPLY[3] + b"\x00", *REPLY[4:]],
        MalformedMessage,
        "QueryReply.mask: frame has 5 bytes",
    ),
    (
        "buffer-huge-shape",
        _with_header(REPLY, _set("arrays.1.shape", [2**40, 2**40])),
        MalformedMessage,
        "QueryReply.mask: frame has 4 bytes",
    ),
    (
        "required-array-nil",
        _with_header(REGIONS, _set("arrays.0", {"name": "label_maps", "dtype": None, "shape": None})),
        MalformedMessage,
        "RegionFeatures.label_maps: nil (None), but the array is required",
    ),
    (
        "nil-with-bytes",
        [*REPLY[:2], b"\x00", *REPLY[3:]],
        MalformedMessage,
        "QueryReply.heatmap: None array with a 1-byte frame",
    ),
    (
        "nil-dtype-only",
        _with_header(REPLY, _set("arrays.0.shape", [1, 1])),
        MalformedMessage,
        "QueryReply.heatmap: dtype and shape must both be nil",
    ),
]


@pytest.mark.parametrize("frames,error,words", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_decode_rejects(frames, error, words):
    with pytest.raises(error) as info:
        decode(frames)
    assert type(info.value) is error  # the specific class, not just any WireError
    assert isinstance(info.value, WireError) and isinstance(info.value, ValueError)
    assert words in str(info.value), str(info.value)


def test_too_large_is_checked_before_parsing():
    frames = encode(
        ImageFrame(image=np.zeros((10, 10, 3), np.uint8), K=np.eye(3), D=np.zeros(0), world_from_camera=np.eye(4)),
        "frames",
    )
    total = sum(len(f) for f in frames)
    assert decode(frames, max_bytes=total)[1].image.shape == (10, 10, 3)
    with pytest.raises(MessageTooLarge, match=f"{total + 0} bytes exceeds max_bytes={total - 1}"):
        decode(frames, max_bytes=total - 1)
    with pytest.raises(MessageTooLarge):  # even garbage is refused by size first
        decode([b"t", b"\xc1" * 100], max_bytes=50)


def test_uint8_dtype_alias_is_accepted():
    frames = _with_header(REPLY, _set("arrays.1.dtype", "<u1"))
    assert decode(frames)[1].mask.dtype == np.uint8


def test_record_float_accepts_an_integer_from_other_encoders():
    frames = _with_header(REPLY, _set("fields.instances.0.centroid", [1, 2, 3]))
    centroid = decode(frames)[1].instances[0]["centroid"]
    assert centroid == [1.0, 2.0, 3.0] and all(type(x) is float for x in centroid)


def test_record_key_order_is_not_significant():
    frames = _with_header(REPLY, _set("fields.instances.1", dict(reversed(INSTANCES[1].items()))))
    back = decode(frames)[1].instances
    assert back == INSTANCES and list(back[1]) == list(INSTANCES[1])  # the schema's order again


def test_float_field_accepts_an_integer_from_other_encoders():
    frames = _with_header(REPLY, _set("fields.seconds", 2))
    seconds = decode(frames)[1].seconds
    assert seconds == 2.0 and isinstance(seconds, float)
