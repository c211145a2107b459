"""Load ``schema.yaml`` (the single source of the wire schema) into typed specs, and render the
generated tables of ``msgs/README.md`` from it (``python -m olsplat_msgs --update msgs/README.md``;
a test fails when the README and the schema differ).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

import yaml

SCHEMA_PREFIX = "olsplat_msgs/"
SCALAR_TYPES = ("str", "int", "float", "bool", "list[str]", "list[dict]", "dict")
ZERO_VALUES: dict[str, Any] = {"str": "", "int": 0, "float": 0.0, "bool": False}
RECORD_SCALARS = ("str", "int", "float", "bool")  # record fields: these and float[N] / int[N]
_FIXED_LIST = re.compile(r"(float|int)\[([1-9][0-9]*)\]")
_RECORD_LIST = re.compile(r"list\[([A-Z][A-Za-z0-9]*)\]")


def fixed_list(kind: str) -> tuple[str, int] | None:
    """``("float", 3)`` for the record field type ``"float[3]"``; None for any other type."""
    match = _FIXED_LIST.fullmatch(kind)
    return (match.group(1), int(match.group(2))) if match else None


@dataclass(frozen=True)
class FieldSpec:
    """One field of a message. ``dtypes`` (numpy dtype strings) and ``shape`` (ints enforced,
    strings name a free dimension) are set for arrays only."""

    name: str
    type: str  # one of SCALAR_TYPES or "array"
    description: str
    optional: bool = False
    default: Any = None  # scalars: the default value; lists/dicts: empty; arrays: None
    choices: tuple | None = None
    dtypes: tuple[str, ...] = ()
    shape: tuple[int | str, ...] = ()
    kinds: tuple[str, ...] = ()  # record fields only: the kinds that have this field (empty = every kind)
    record: RecordSpec | None = None  # list[<Record>] fields only: the record of the items

    @property
    def is_array(self) -> bool:
        return self.type == "array"

    def type_text(self) -> str:
        """Human-readable type, as the README tables show it."""
        if self.is_array:
            names = " or ".join(dtype_name(d) for d in self.dtypes)
            text = f"array {names} [{', '.join(str(s) for s in self.shape)}]"
        else:
            text = self.type
        return text + (", optional" if self.optional else "")


@dataclass(frozen=True)
class RecordSpec:
    """A record: a typed map carried inside a message field (``list[<Record>]``). With a ``tag``
    the record comes in kinds, named by the value of its tag field, each with its own set of
    fields (``fields_of``); a map on the wire holds exactly its kind's fields."""

    name: str
    description: str
    fields: tuple[FieldSpec, ...]
    tag: str | None = None

    @property
    def kinds(self) -> tuple[str, ...]:
        """The kinds (the tag field's choices, in schema order); ``()`` for a record without a tag."""
        if self.tag is None:
            return ()
        return tuple(next(f for f in self.fields if f.name == self.tag).choices or ())

    def fields_of(self, kind: str | None = None) -> tuple[FieldSpec, ...]:
        """The fields a map of ``kind`` holds, in schema order (every field without a tag)."""
        return tuple(f for f in self.fields if not f.kinds or kind in f.kinds)


@dataclass(frozen=True)
class MessageSpec:
    """One message: its short name (``ImageFrame``), description and own fields (after the common ones)."""

    name: str
    description: str
    fields: tuple[FieldSpec, ...]

    @property
    def schema_name(self) -> str:
        return SCHEMA_PREFIX + self.name

    @property
    def scalar_fields(self) -> tuple[FieldSpec, ...]:
        return tuple(f for f in self.fields if not f.is_array)

    @property
    def array_fields(self) -> tuple[FieldSpec, ...]:
        return tuple(f for f in self.fields if f.is_array)


@dataclass(frozen=True)
class Schema:
    version: int
    dtypes: dict[str, str]  # name ("float32") -> numpy dtype string ("<f4")
    header: tuple[FieldSpec, ...]
    common: tuple[FieldSpec, ...]
    messages: dict[str, MessageSpec]  # short name -> spec, in file order
    records: dict[str, RecordSpec]  # name -> spec, in file order


def dtype_name(dtype_str: str) -> str:
    """``"<f4"`` -> ``"float32"`` for the dtypes the schema allows."""
    for name, text in load_schema().dtypes.items():
        if text == dtype_str:
            return name
    raise ValueError(f"dtype {dtype_str!r} is not one of the wire dtypes")


def _field(raw: dict, dtypes: dict[str, str], where: str, records: dict[str, RecordSpec] | None = None) -> FieldSpec:
    unknown = set(raw) - {"name", "type", "description", "optional", "default", "choices", "dtype", "shape"}
    if unknown or not {"name", "type", "description"} <= set(raw):
        raise ValueError(f"schema.yaml {where}: bad field keys {sorted(raw)}")
    kind = raw["type"]
    listed = _RECORD_LIST.fullmatch(kind)
    if listed:
        record = (records or {}).get(listed.group(1))
        if record is None:
            raise ValueError(f"schema.yaml {where}.{raw['name']}: unknown record in type {kind!r}")
        if set(raw) - {"name", "type", "description"}:
            raise ValueError(f"schema.yaml {where}.{raw['name']}: a list of records takes no other keys")
        return FieldSpec(raw["name"], kind, raw["description"], record=record)
    if kind not in (*SCALAR_TYPES, "array"):
        raise ValueError(f"schema.yaml {where}.{raw['name']}: unknown type {kind!r}")
    choices = tuple(raw["choices"]) if "choices" in raw else None
    if kind == "array":
        if "default" in raw or choices:
            raise ValueError(f"schema.yaml {where}.{raw['name']}: arrays take no default or choices")
        bad = [d for d in raw["dtype"] if d not in dtypes]
        if bad or not raw["dtype"] or not raw["shape"]:
            raise ValueError(f"schema.yaml {where}.{raw['name']}: bad dtype {raw['dtype']} or shape {raw.get('shape')}")
        return FieldSpec(
            raw["name"],
            kind,
            raw["description"],
            bool(raw.get("optional", False)),
            None,
            None,
            tuple(dtypes[d] for d in raw["dtype"]),
            tuple(raw["shape"]),
        )
    if kind in ("list[str]", "list[dict]", "dict"):
        if "default" in raw:
            raise ValueError(f"schema.yaml {where}.{raw['name']}: containers always default to empty")
        default = None
    else:
        default = raw.get("default", None if raw.get("optional") else ZERO_VALUES[kind])
    return FieldSpec(raw["name"], kind, raw["description"], bool(raw.get("optional", False)), default, choices)


def _record(name: str, raw: dict) -> RecordSpec:
    if set(raw) - {"description", "tag", "fields"} or not {"description", "fields"} <= set(raw):
        raise ValueError(f"schema.yaml records.{name}: bad keys {sorted(raw)}")
    fields = []
    for f in raw["fields"]:
        where = f"records.{name}.{f.get('name')}"
        if set(f) - {"name", "type", "description", "choices", "kinds"} or not {"name", "type", "description"} <= set(
            f
        ):
            raise ValueError(f"schema.yaml {where}: bad field keys {sorted(f)} (record fields are never optional)")
        if f["type"] not in RECORD_SCALARS and fixed_list(f["type"]) is None:
            raise ValueError(
                f"schema.yaml {where}: type {f['type']!r} is not one of {RECORD_SCALARS} or float[N], int[N]"
            )
        choices = tuple(f["choices"]) if "choices" in f else None
        fields.append(
            FieldSpec(f["name"], f["type"], f["description"], choices=choices, kinds=tuple(f.get("kinds", ())))
        )
    names = [f.name for f in fields]
    if len(set(names)) != len(names):
        raise ValueError(f"schema.yaml records.{name}: duplicate field names {names}")
    record = RecordSpec(name, raw["description"], tuple(fields), raw.get("tag"))
    tag = next((f for f in fields if f.name == record.tag), None)
    if record.tag is not None and (tag is None or tag.type != "str" or not tag.choices or tag.kinds):
        raise ValueError(
            f"schema.yaml records.{name}: tag {record.tag!r} must be a str field with choices, in every kind"
        )
    for f in fields:
        if set(f.kinds) - set(record.kinds) or (f.kinds and record.tag is None):
            raise ValueError(
                f"schema.yaml records.{name}.{f.name}: kinds {list(f.kinds)} not among {list(record.kinds)}"
            )
    return record


@cache
def load_schema() -> Schema:
    """Parse and check ``schema.yaml`` (cached; the file ships as package data)."""
    raw = yaml.safe_load(resources.files("olsplat_msgs").joinpath("schema.yaml").read_text(encoding="utf-8"))
    dtypes = dict(raw["dtypes"])
    records = {name: _record(name, body) for name, body in raw.get("records", {}).items()}
    messages = {}
    for name, body in raw["messages"].items():
        fields = tuple(_field(f, dtypes, name, records) for f in body["fields"])
        names = [f.name for f in fields]
        if len(set(names)) != len(names) or set(names) & {"stamp_ns", "seq", "frame_id"}:
            raise ValueError(f"schema.yaml {name}: duplicate field names or a common field repeated: {names}")
        messages[name] = MessageSpec(name, body["description"], fields)
    return Schema(
        version=int(raw["version"]),
        dtypes=dtypes,
        header=tuple(_field(f, dtypes, "header") for f in raw["header"]),
        common=tuple(_field(f, dtypes, "common") for f in raw["common"]),
        messages=messages,
        records=records,
    )


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|")


def _default_text(spec: FieldSpec) -> str:
    if spec.is_array:
        return "None (nil)" if spec.optional else "required"
    if spec.type.startswith("list["):
        return "[]"
    if spec.type == "dict":
        return "{}"
    value = spec.default
    if value is None:
        return "None (nil)"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float) and math.isnan(value):
        return "NaN"
    if isinstance(value, str):
        return f'"{value}"'
    return str(value)


def header_table() -> str:
    """The keys of the msgpack header map, as the README's ``header`` block."""
    lines = ["| key | msgpack type | description |", "|---|---|---|"]
    lines += [f"| `{f.name}` | {_cell(f.type)} | {_cell(f.description)} |" for f in load_schema().header]
    return "\n".join(lines) + "\n"


def message_tables() -> str:
    """One table per message (common fields first), as the README's ``messages`` block."""
    schema = load_schema()
    lines = []
    for msg in schema.messages.values():
        lines += [
            f"### {msg.name}",
            "",
            f'Schema `"{msg.schema_name}"`. {msg.description}',
            "",
            "| # | field | type | default | where | description |",
            "|---|---|---|---|---|---|",
        ]
        array_index = 0
        for i, f in enumerate([*schema.common, *msg.fields]):
            if f.is_array:
                where = f"frame {2 + array_index}"
                array_index += 1
            else:
                where = "header" if i < len(schema.common) else "header.fields"
            choices = f" (one of {', '.join(map(str, f.choices))})" if f.choices else ""
            cells = [str(i), f"`{f.name}`", _cell(f.type_text()), _cell(_default_text(f)), where]
            lines.append(f"| {' | '.join(cells)} | {_cell(f.description + choices)} |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def record_tables() -> str:
    """One table per record, as the README's ``records`` block."""
    schema = load_schema()
    lines = []
    for record in schema.records.values():
        used_by = [
            f"`{msg.name}.{f.name}`" for msg in schema.messages.values() for f in msg.fields if f.record is record
        ]
        kinds = (
            f" The `{record.tag}` key names the kind ({', '.join(record.kinds)}) and so which keys the map holds."
            if record.tag
            else ""
        )
        lines += [
            f"#### {record.name} (record)",
            "",
            f"In {', '.join(used_by) or 'no message yet'}. {record.description}{kinds}",
            "",
            "| # | key | kinds | type | description |",
            "|---|---|---|---|---|",
        ]
        for i, f in enumerate(record.fields):
            choices = f" (one of {', '.join(map(str, f.choices))})" if f.choices else ""
            where = ", ".join(f.kinds) if f.kinds else "all"
            lines.append(f"| {i} | `{f.name}` | {where} | {_cell(f.type)} | {_cell(f.description + choices)} |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


GENERATED_BLOCKS = {"header": header_table, "messages": message_tables, "records": record_tables}


def _markers(block: str) -> tuple[str, str]:
    return (
        f"<!-- BEGIN GENERATED: {block} (python -m olsplat_msgs --update msgs/README.md) -->",
        f"<!-- END GENERATED: {block} -->",
    )


def readme_block(text: str, block: str) -> str:
    """The content of a generated block of a README (between its markers, exclusive)."""
    begin, end = _markers(block)
    return text[text.index(begin) + len(begin) : text.index(end)].strip("\n") + "\n"


def update_readme(text: str) -> str:
    """``text`` with every generated block replaced by what the schema gives now."""
    for block, render in GENERATED_BLOCKS.items():
        begin, end = _markers(block)
        start, stop = text.index(begin) + len(begin), text.index(end)
        text = text[:start] + "\n\n" + render() + "\n" + text[stop:]
    return text
