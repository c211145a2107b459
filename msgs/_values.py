"""Checks of non-array field values (records included), shared by both directions of the codec.

``convert=True`` (encode) also turns numpy scalars/arrays and tuples into msgpack-native values
and raises ``TypeError``/``ValueError`` (a programming error in the sender);
``convert=False`` (decode) only checks and raises ``MalformedMessage`` (bad data on the wire).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import MalformedMessage
from .schema import FieldSpec, RecordSpec, fixed_list

INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1
MSGPACK_INT_MAX = 2**64 - 1  # msgpack's unsigned 64-bit integers
MAX_DEPTH = 32  # nesting of maps/lists inside a field: deep enough for any real use, bounded for a hostile sender


def _fail(convert: bool, message: str, kind: type[Exception] = TypeError) -> Exception:
    return kind(message) if convert else MalformedMessage(message)


def native(value: Any, where: str, convert: bool, depth: int = 0) -> Any:
    """``value`` as msgpack-native data: None, bool, int, float, str, lists and str-keyed maps.
    Bytes and extension types are refused so that every client can read every field as JSON-like data."""
    if convert and isinstance(value, np.ndarray):
        value = value.tolist()
    elif convert and isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        if not INT64_MIN <= value <= MSGPACK_INT_MAX:
            raise _fail(convert, f"{where}: integer {value} outside the msgpack range", ValueError)
        return int(value)
    if isinstance(value, float):
        return float(value)
    if depth >= MAX_DEPTH:
        raise _fail(convert, f"{where}: nested deeper than {MAX_DEPTH} levels", ValueError)
    if convert and isinstance(value, tuple):
        value = list(value)
    if isinstance(value, list):
        return [native(v, f"{where}[{i}]", convert, depth + 1) for i, v in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise _fail(convert, f"{where}: map key {key!r} is a {type(key).__name__}, keys must be str")
            out[key] = native(item, f"{where}.{key}", convert, depth + 1)
        return out
    raise _fail(convert, f"{where}: a {type(value).__name__} is not a msgpack-native value")


def field_value(spec: FieldSpec, value: Any, where: str, convert: bool) -> Any:
    """The checked value of a non-array field (see module docstring for ``convert``)."""
    if value is None:
        if spec.optional:
            return None
        raise _fail(convert, f"{where}: None, but the field is not optional ({spec.type})")
    if convert and isinstance(value, np.generic):
        value = value.item()
    kind = spec.type
    if kind == "str":
        if not isinstance(value, str):
            raise _fail(convert, f"{where}: expected str, got {type(value).__name__} {value!r:.80}")
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(convert, f"{where}: expected int, got {type(value).__name__} {value!r:.80}")
        if not INT64_MIN <= value <= INT64_MAX:
            raise _fail(convert, f"{where}: {value} outside the signed 64-bit range", ValueError)
        value = int(value)
    elif kind == "float":
        # an int is accepted for a float field: other languages' encoders may write 0 for 0.0
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(convert, f"{where}: expected float, got {type(value).__name__} {value!r:.80}")
        value = float(value)
    elif kind == "bool":
        if not isinstance(value, bool):
            raise _fail(convert, f"{where}: expected bool, got {type(value).__name__} {value!r:.80}")
    elif spec.record is not None:  # list[<Record>]
        if convert and isinstance(value, tuple):
            value = list(value)
        if not isinstance(value, list):
            raise _fail(convert, f"{where}: expected {kind} (an array of maps), got {type(value).__name__}")
        value = [record_value(spec.record, item, f"{where}[{i}]", convert) for i, item in enumerate(value)]
    elif (fixed := fixed_list(kind)) is not None:  # float[N], int[N] (record fields)
        item_kind, length = fixed
        if convert and isinstance(value, (tuple, np.ndarray)):
            value = list(value)
        if not isinstance(value, list) or len(value) != length:
            size = f" of {len(value)} items" if isinstance(value, list) else ""
            raise _fail(convert, f"{where}: expected {kind} ({length} numbers), got {type(value).__name__}{size}")
        item_spec = _ITEM_SPECS[item_kind]
        value = [field_value(item_spec, item, f"{where}[{i}]", convert) for i, item in enumerate(value)]
    else:
        if convert and isinstance(value, tuple):
            value = list(value)
        container = dict if kind == "dict" else list
        if not isinstance(value, container):
            raise _fail(convert, f"{where}: expected {kind}, got {type(value).__name__}")
        value = native(value, where, convert)
        item_type: type | None = {"list[str]": str, "list[dict]": dict}.get(kind)
        if item_type is not None:
            for i, item in enumerate(value):
                if not isinstance(item, item_type):
                    raise _fail(convert, f"{where}[{i}]: expected {item_type.__name__}, got {type(item).__name__}")
    if spec.choices is not None and value not in spec.choices:
        raise _fail(convert, f"{where}: {value!r} is not one of {list(spec.choices)}", ValueError)
    return value


_ITEM_SPECS = {kind: FieldSpec("item", kind, "") for kind in ("int", "float")}


def record_value(record: RecordSpec, value: Any, where: str, convert: bool) -> dict:
    """The checked map of one record: exactly the fields of its kind (all of them, none nil, no
    others), each checked as a field; returned as a new dict in schema order."""
    if not isinstance(value, dict):
        raise _fail(convert, f"{where}: expected a map (record {record.name}), got {type(value).__name__}")
    kind = None
    if record.tag is not None:
        if record.tag not in value:
            raise _fail(convert, f"{where}: record {record.name} without its {record.tag!r} key", ValueError)
        tag = next(f for f in record.fields if f.name == record.tag)
        kind = field_value(tag, value[record.tag], f"{where}.{record.tag}", convert)
    fields = record.fields_of(kind)
    names = [f.name for f in fields]
    if len(value) != len(names) or any(name not in value for name in names):
        missing = [name for name in names if name not in value]
        extra = ", ".join(f"{key!r:.40}" for key in value if key not in names)
        of_kind = f" of kind {kind!r}" if kind is not None else ""
        raise _fail(
            convert,
            f"{where}: record {record.name}{of_kind} needs exactly the keys {names}; "
            f"missing {missing}, unexpected [{extra}]",
            ValueError,
        )
    return {f.name: field_value(f, value[f.name], f"{where}.{f.name}", convert) for f in fields}
