"""The dataclasses, the record TypedDicts, the README and its worked examples all agree with
schema.yaml and the encoder."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import typing
from pathlib import Path

import msgpack
import numpy as np
import pytest

import olsplat_msgs
from olsplat_msgs import MESSAGES, Instance2D, Instance3D, QueryReply, StatusRequest, decode, encode, load_schema
from olsplat_msgs import messages as messages_module
from olsplat_msgs.messages import RECORDS, check_against_schema
from olsplat_msgs.schema import GENERATED_BLOCKS, _record, readme_block, record_tables, update_readme

README = Path(olsplat_msgs.__file__).with_name("README.md")
SCHEMA = load_schema()


def test_classes_agree_with_schema():
    assert check_against_schema() == []


@pytest.mark.parametrize("name", list(SCHEMA.messages))
def test_class_fields_match_schema_field_by_field(name):
    """Independent of check_against_schema: names, order and annotations from the dataclass itself."""
    cls = MESSAGES[f"olsplat_msgs/{name}"]
    got = [(f.name, f.type) for f in dataclasses.fields(cls)]
    want = [(f.name, f.type) for f in SCHEMA.common] + [
        (f.name, "np.ndarray | None" if f.is_array else f.type) for f in SCHEMA.messages[name].fields
    ]
    assert got == want
    instance = cls()
    for f in SCHEMA.messages[name].fields:
        value = getattr(instance, f.name)
        if f.is_array:
            assert value is None
        elif isinstance(f.default, float) and math.isnan(f.default):
            assert math.isnan(value)
        else:
            assert value == ([] if f.type.startswith("list[") else {"dict": {}}.get(f.type, f.default))
            assert type(value) is type(f.default) or f.default is None


def test_schema_basics():
    assert SCHEMA.version == 5 == olsplat_msgs.VERSION
    assert set(SCHEMA.dtypes.values()) == {"|u1", "<u2", "<i4", "<i8", "<f2", "<f4", "<f8"}
    for name, text in SCHEMA.dtypes.items():
        assert np.dtype(name).newbyteorder("<").str == text
    assert [f.name for f in SCHEMA.header] == ["schema", "version", "stamp_ns", "seq", "frame_id", "fields", "arrays"]
    for msg in SCHEMA.messages.values():
        for f in msg.fields:
            assert f.description.strip(), f"{msg.name}.{f.name} has no description"


def test_instance_record_in_the_schema():
    """The documented record, spelled out (a change here is a wire change: see README section 6)."""
    record = SCHEMA.records["Instance"]
    assert record.tag == "kind" and record.kinds == ("3d", "2d")
    assert [(f.name, f.type) for f in record.fields_of("3d")] == [
        ("id", "int"),
        ("kind", "str"),
        ("n_gaussians", "int"),
        ("centroid", "float[3]"),
        ("box_min", "float[3]"),
        ("box_max", "float[3]"),
        ("latitude", "float"),
        ("longitude", "float"),
        ("altitude", "float"),
        ("footprint", "float[8]"),
        ("box_altitude", "float[2]"),
    ]
    assert [(f.name, f.type) for f in record.fields_of("2d")] == [
        ("id", "int"),
        ("kind", "str"),
        ("box2d", "int[4]"),
        ("centre_px", "float[2]"),
        ("area_px", "int"),
    ]
    (instances,) = [f for f in SCHEMA.messages["QueryReply"].fields if f.name == "instances"]
    assert instances.type == "list[Instance]" and instances.record is record
    for f in record.fields:
        assert f.description.strip() and not f.optional, f.name
    assert "metres" in record.fields[3].description and "(0.5, 0.5)" in record.fields[12].description
    assert "degrees" in record.fields[6].description and "counter-clockwise" in record.fields[9].description


def test_record_typeddicts_match_schema_key_by_key():
    """Independent of check_against_schema: each kind's TypedDict has the schema's keys in order,
    all required, with the Python type of each schema type."""
    python = {
        "int": int,
        "float": float,
        "str": str,
        "float[2]": list[float],
        "float[3]": list[float],
        "float[8]": list[float],
        "int[4]": list[int],
    }
    assert list(RECORDS) == list(SCHEMA.records)
    for cls, kind in ((Instance3D, "3d"), (Instance2D, "2d")):
        assert RECORDS["Instance"][kind] is cls
        specs = SCHEMA.records["Instance"].fields_of(kind)
        hints = typing.get_type_hints(cls)
        assert list(hints) == [f.name for f in specs]
        assert hints == {f.name: typing.Literal[kind] if f.name == "kind" else python[f.type] for f in specs}
        assert cls.__required_keys__ == frozenset(hints)
    assert typing.get_args(olsplat_msgs.Instance) == (Instance3D, Instance2D)
    assert dataclasses.fields(QueryReply)[10].type == "list[Instance]"


def test_check_against_schema_catches_a_record_drift(monkeypatch):
    class Wrong(typing.TypedDict):
        id: int
        kind: typing.Literal["2d"]
        box2d: list[float]  # the schema says int[4]
        centre_px: list[float]
        area_px: int

    monkeypatch.setitem(messages_module.RECORDS, "Instance", {"3d": Instance3D, "2d": Wrong})
    problems = check_against_schema()
    assert len(problems) == 1 and problems[0].startswith("Wrong: keys and types")
    monkeypatch.setitem(messages_module.RECORDS, "Instance", {"3d": Instance3D})
    assert check_against_schema() == ["record Instance: classes for kinds ['3d'], schema has ['3d', '2d']"]


@pytest.mark.parametrize(
    "raw,words",
    [
        ({"description": "d", "fields": [{"name": "a", "type": "list[str]", "description": "d"}]}, "is not one of"),
        ({"description": "d", "fields": [{"name": "a", "type": "float[0]", "description": "d"}]}, "is not one of"),
        (
            {"description": "d", "fields": [{"name": "a", "type": "int", "description": "d", "optional": True}]},
            "never optional",
        ),
        (
            {"description": "d", "tag": "k", "fields": [{"name": "k", "type": "str", "description": "d"}]},
            "must be a str field with choices",
        ),
        (
            {"description": "d", "fields": [{"name": "a", "type": "int", "description": "d", "kinds": ["x"]}]},
            "kinds ['x'] not among []",
        ),
        (
            {"description": "d", "fields": [{"name": "a", "type": "int", "description": "d"}] * 2},
            "duplicate field names",
        ),
        ({"fields": []}, "bad keys"),
    ],
)
def test_bad_record_definitions_are_refused(raw, words):
    with pytest.raises(ValueError) as info:
        _record("R", raw)
    assert words in str(info.value)


@pytest.mark.parametrize("block", list(GENERATED_BLOCKS))
def test_readme_tables_match_schema(block):
    text = README.read_text(encoding="utf-8")
    assert readme_block(text, block) == GENERATED_BLOCKS[block](), "run: python -m olsplat_msgs --update msgs/README.md"


def test_readme_is_up_to_date_as_a_whole():
    text = README.read_text(encoding="utf-8")
    assert update_readme(text) == text


def test_readme_lists_every_message():
    text = README.read_text(encoding="utf-8")
    for name in SCHEMA.messages:
        assert f"### {name}\n" in text
    for f in SCHEMA.messages["RegionFeatures"].fields:
        assert f"`{f.name}`" in text


def test_readme_documents_every_record_field_with_its_kinds_and_type():
    block = readme_block(README.read_text(encoding="utf-8"), "records")
    assert block == record_tables()
    for record in SCHEMA.records.values():
        assert f"#### {record.name} (record)\n" in block
        for i, f in enumerate(record.fields):
            kinds = ", ".join(f.kinds) or "all"
            assert f"| {i} | `{f.name}` | {kinds} | {f.type} | {f.description}" in block
    assert "In `QueryReply.instances`." in block
    assert "| 10 | `instances` | list[Instance] | [] | header.fields |" in readme_block(
        README.read_text(encoding="utf-8"), "messages"
    )
    assert "score" not in block  # the old description's field that was never sent


def _fenced_after(text: str, marker: str) -> str:
    start = text.index(marker)
    match = re.search(r"```\w*\n(.*?)```", text[start:], re.S)
    assert match, marker
    return match.group(1)


def _hex_frames(block: str) -> list[bytes]:
    """Frames of an annotated hex dump: 'frame N: ...' starts a frame, then 'xx xx  # comment' lines."""
    frames: list[bytearray] = []
    for line in block.splitlines():
        if line.startswith("frame "):
            frames.append(bytearray())
            continue
        data = line.split("#", 1)[0].split()
        frames[-1].extend(bytes.fromhex("".join(data)))
    return [bytes(f) for f in frames]


def test_worked_example_bytes_match_the_encoder():
    text = README.read_text(encoding="utf-8")
    msg = StatusRequest(stamp_ns=1700000000123456789, seq=7, frame_id="gs", request_id="r1")
    assert _hex_frames(_fenced_after(text, "<!-- worked example: StatusRequest -->")) == encode(msg, "query")


def test_worked_example_with_arrays_matches_the_encoder():
    text = README.read_text(encoding="utf-8")
    msg = QueryReply(
        seq=1,
        frame_id="query_server",
        request_id="r2",
        text="road",
        view="v000",
        map_version=3,
        mask=np.array([[0, 1, 1], [0, 0, 1]], np.uint8),
        seconds=0.25,
    )
    frames = encode(msg, "query")
    header = json.loads(_fenced_after(text, "<!-- worked example: QueryReply header -->"))
    assert header == msgpack.unpackb(frames[1])
    assert msgpack.packb(header) == frames[1]  # same key order too
    assert _hex_frames(_fenced_after(text, "<!-- worked example: QueryReply arrays -->")) == frames[2:]
    assert "00 00 80 3f 00 00 00 c0" == " ".join(f"{b:02x}" for b in np.array([1.0, -2.0], "<f4").tobytes())


def test_worked_example_instances_are_valid_records():
    """The README's Instance example, sent as a receiver would get it, decodes unchanged."""
    example = json.loads(_fenced_after(README.read_text(encoding="utf-8"), "<!-- worked example: Instance -->"))
    assert [i["kind"] for i in example] == ["3d", "2d"]
    frames = encode(QueryReply(request_id="r", instances=example), "query")
    assert msgpack.unpackb(frames[1])["fields"]["instances"] == example
    assert decode(frames)[1].instances == example
