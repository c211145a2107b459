"""The dataclasses, the README and its worked examples all agree with schema.yaml and the encoder."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import msgpack
import numpy as np
import pytest

import olsplat_msgs
from olsplat_msgs import MESSAGES, QueryReply, StatusRequest, encode, load_schema
from olsplat_msgs.messages import check_against_schema
from olsplat_msgs.schema import GENERATED_BLOCKS, readme_block, update_readme

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
        (f.name, ("np.ndarray | None" if f.optional else "np.ndarray") if f.is_array else f.type)
        for f in SCHEMA.messages[name].fields
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
            assert value == {"list[str]": [], "list[dict]": [], "dict": {}}.get(f.type, f.default)
            assert type(value) is type(f.default) or f.default is None


def test_schema_basics():
    assert SCHEMA.version == 1 == olsplat_msgs.VERSION
    assert set(SCHEMA.dtypes.values()) == {"|u1", "<u2", "<i4", "<i8", "<f2", "<f4", "<f8"}
    for name, text in SCHEMA.dtypes.items():
        assert np.dtype(name).newbyteorder("<").str == text
    assert [f.name for f in SCHEMA.header] == ["schema", "version", "stamp_ns", "seq", "frame_id", "fields", "arrays"]
    for msg in SCHEMA.messages.values():
        for f in msg.fields:
            assert f.description.strip(), f"{msg.name}.{f.name} has no description"


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
