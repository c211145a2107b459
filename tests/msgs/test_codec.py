"""Round trips of every message through encode/decode, and what encode refuses."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from olsplat_msgs import (
    MESSAGES,
    DiagnosticStatus,
    ImageFrame,
    Instance2D,
    Instance3D,
    QueryReply,
    QueryRequest,
    RegionFeatures,
    StatusRequest,
    decode,
    encode,
    load_schema,
)

from .samples import assert_same, sample_messages

SAMPLES = sample_messages()
INSTANCE_2D = Instance2D(id=0, kind="2d", box2d=[0, 1, 2, 3], centre_px=[1.0, 2.0], area_px=4)


@pytest.mark.parametrize("name,msg", SAMPLES, ids=[s[0] for s in SAMPLES])
def test_round_trip(name, msg):
    frames = encode(msg, "uav1/frames")
    assert all(isinstance(f, bytes) for f in frames)
    topic, back = decode(frames)
    assert topic == "uav1/frames"
    assert_same(msg, back)
    # a second pass gives the same bytes: the encoding is deterministic
    assert encode(back, topic) == frames


def test_every_message_class_has_a_sample():
    assert {type(m) for _, m in SAMPLES} == set(MESSAGES.values())


@pytest.mark.parametrize("cls", list(MESSAGES.values()), ids=list(MESSAGES))
def test_frame_count_is_fixed_per_message(cls):
    arrays = load_schema().messages[cls.__name__].array_fields
    for msg in (m for _, m in SAMPLES if type(m) is cls):
        assert len(encode(msg, "t")) == 2 + len(arrays)


def test_header_layout():
    msg = next(m for n, m in SAMPLES if n == "reply-none-arrays")
    header = msgpack.unpackb(encode(msg, "query")[1])
    assert list(header) == ["schema", "version", "stamp_ns", "seq", "frame_id", "fields", "arrays"]
    assert header["schema"] == "olsplat_msgs/QueryReply" and header["version"] == 5
    assert "heatmap" not in header["fields"] and header["fields"]["status"] == "no_map"
    assert header["arrays"][0] == {"name": "heatmap", "dtype": None, "shape": None}


def test_decoded_arrays_are_read_only_zero_copy_views():
    msg = next(m for n, m in SAMPLES if n == "image")
    frames = [bytearray(f) for f in encode(msg, "frames")]
    _, back = decode(frames)
    assert not back.image.flags.writeable
    with pytest.raises(ValueError):
        back.image[0, 0, 0] = 1
    frames[2][0] = (int(msg.image[0, 0, 0]) + 1) % 256  # the decoded array sees the buffer: no copy was made
    assert back.image[0, 0, 0] == frames[2][0]


def test_decode_accepts_memoryviews_and_float16():
    msg = next(m for n, m in SAMPLES if n == "regions-f16")
    _, back = decode([memoryview(f) for f in encode(msg, "regions")])
    assert back.features.dtype == np.float16
    assert np.array_equal(back.features, msg.features)


def test_encode_normalises_layout_and_byte_order():
    rng = np.random.default_rng(0)
    big = rng.random((5, 7)).astype(">f4")
    transposed = rng.random((7, 5)).astype(np.float32).T  # Fortran-ordered view
    for heatmap in (big, transposed):
        _, back = decode(encode(QueryReply(heatmap=heatmap), "query"))
        assert back.heatmap.dtype == np.dtype("<f4")
        assert np.array_equal(back.heatmap, heatmap)


def test_encode_converts_numpy_scalars_and_tuples():
    msg = DiagnosticStatus(
        seq=np.int64(4),
        node="n",
        level=np.int32(1),
        values={"rate_hz": np.float32(2.5), "drops": np.int64(3), "v": np.arange(2)},
    )
    _, back = decode(encode(msg, "diagnostics"))
    assert back.seq == 4 and back.level == 1 and type(back.level) is int
    assert back.values == {"rate_hz": 2.5, "drops": 3, "v": [0, 1]}
    _, back = decode(encode(QueryRequest(negatives=("a", "b"), threshold=1), "query"))
    assert back.negatives == ["a", "b"] and back.threshold == 1.0 and isinstance(back.threshold, float)
    assert math.isnan(decode(encode(QueryRequest(), "query"))[1].threshold)


def _image(**changes):
    fields = dict(
        image=np.zeros((2, 3, 3), np.uint8), K=np.eye(3), D=np.zeros(0), world_from_camera=np.eye(4), width=3, height=2
    )
    fields.update(changes)
    return ImageFrame(**fields)


@pytest.mark.parametrize(
    "msg,error,words",
    [
        (_image(K=np.eye(3, dtype=np.float32)), TypeError, "ImageFrame.K: dtype float32"),
        (_image(K=np.eye(4)), ValueError, "ImageFrame.K: shape [4, 4], axis 0 must be 3"),
        (_image(image=np.zeros((2, 3), np.uint8)), ValueError, "ImageFrame.image: rank 2"),
        (_image(image=None), ValueError, "ImageFrame.image: required array is None"),
        (_image(width=2.0), TypeError, "ImageFrame.width: expected int"),
        (_image(width=True), TypeError, "ImageFrame.width: expected int"),
        (_image(name=b"x"), TypeError, "ImageFrame.name: expected str"),
        (_image(seq=-1), TypeError, "ImageFrame.seq"),
        (_image(stamp_ns=2**63), TypeError, "ImageFrame.stamp_ns"),
        (_image(frame_id=None), TypeError, "ImageFrame.frame_id"),
        (_image(width=2**63), ValueError, "ImageFrame.width"),
        (
            RegionFeatures(
                label_maps=np.zeros((1, 2, 3), np.int32),
                level_sizes=np.zeros(1, np.int32),
                features=np.zeros((1, 4), np.float64),
                image=np.zeros((2, 3, 3), np.uint8),
                K=np.eye(3),
                D=np.zeros(0),
                world_from_camera=np.eye(4),
            ),
            TypeError,
            "expected float16 or float32",
        ),
        (QueryReply(status="fine"), ValueError, "QueryReply.status: 'fine' is not one of"),
        (DiagnosticStatus(level=7), ValueError, "DiagnosticStatus.level"),
        (DiagnosticStatus(values={1: 2}), TypeError, "keys must be str"),
        (DiagnosticStatus(values={"x": object()}), TypeError, "DiagnosticStatus.values.x"),
        (DiagnosticStatus(values={"x": b"raw"}), TypeError, "DiagnosticStatus.values.x"),
        (QueryRequest(negatives=["a", 3]), TypeError, "QueryRequest.negatives[1]"),
        (QueryReply(instances=[1]), TypeError, "QueryReply.instances[0]: expected a map (record Instance)"),
        (QueryReply(instances=[{"id": 0}]), ValueError, "QueryReply.instances[0]: record Instance without its 'kind'"),
        (QueryReply(instances=[{**INSTANCE_2D, "kind": "3D"}]), ValueError, "instances[0].kind: '3D' is not one of"),
        (QueryReply(instances=[{**INSTANCE_2D, "score": 0.5}]), ValueError, "unexpected ['score']"),
        (QueryReply(instances=[{**INSTANCE_2D, "box2d": [0, 1, 2]}]), TypeError, "box2d: expected int[4]"),
        (QueryReply(instances=[{**INSTANCE_2D, "box2d": [0, 1, 2, 3.0]}]), TypeError, "box2d[3]: expected int"),
        (QueryReply(instances=[{**INSTANCE_2D, "area_px": None}]), TypeError, "area_px: None"),
        (QueryRequest(heatmap=1), TypeError, "QueryRequest.heatmap: expected bool"),
    ],
)
def test_encode_refuses_what_does_not_fit_the_schema(msg, error, words):
    with pytest.raises(error) as info:
        encode(msg, "t")
    assert words in str(info.value)


def test_encode_refuses_bad_topic_and_foreign_objects():
    with pytest.raises(ValueError, match="topic"):
        encode(StatusRequest(), "")
    with pytest.raises(TypeError, match="not an olsplat_msgs message"):
        encode({"request_id": "x"}, "query")


def test_deep_nesting_is_refused():
    value: list = []
    for _ in range(40):
        value = [value]
    with pytest.raises(ValueError, match="nested deeper"):
        encode(DiagnosticStatus(values={"deep": value}), "d")


def test_records_from_numpy_and_tuples_are_written_as_plain_lists():
    """What the query server's numbers look like before encode: numpy scalars and arrays, tuples."""
    centre = np.array([1.0, 2.0, 3.0], np.float32)
    sent = QueryReply(
        instances=[
            Instance3D(
                id=np.int64(0),
                kind="3d",
                n_gaussians=np.int32(25),
                centroid=centre,
                box_min=(np.float64(0.5), 1, 2.0),
                box_max=centre + 1,
                latitude=np.float64(47.5),
                longitude=8,
                altitude=np.float32(400.5),
                footprint=np.arange(8, dtype=np.float64),
                box_altitude=(np.float64(400.0), 401),
            ),
            Instance2D(
                id=0, kind="2d", box2d=tuple(np.arange(4)), centre_px=(0.5, np.float32(1.5)), area_px=np.int64(9)
            ),
        ]
    )
    frames = encode(sent, "query")
    raw = msgpack.unpackb(frames[1])["fields"]["instances"]
    assert raw == [
        {
            "id": 0,
            "kind": "3d",
            "n_gaussians": 25,
            "centroid": [1.0, 2.0, 3.0],
            "box_min": [0.5, 1.0, 2.0],
            "box_max": [2.0, 3.0, 4.0],
            "latitude": 47.5,
            "longitude": 8.0,
            "altitude": 400.5,
            "footprint": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0],
            "box_altitude": [400.0, 401.0],
        },
        {"id": 0, "kind": "2d", "box2d": [0, 1, 2, 3], "centre_px": [0.5, 1.5], "area_px": 9},
    ]
    back = decode(frames)[1].instances
    assert back == raw and all(type(x) is float for x in back[0]["box_min"])
    assert encode(decode(frames)[1], "query") == frames
