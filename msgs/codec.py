"""``encode``/``decode``: messages <-> multipart frames ``[topic][msgpack header][array buffers...]``.

The layout is specified in ``msgs/README.md``. In short: frame 0 is the topic (UTF-8, non-empty);
frame 1 a msgpack map ``{schema, version, stamp_ns, seq, frame_id, fields, arrays}``; then exactly
one frame per array field of the message, in schema order, holding the array's bytes in C order
(an empty frame, with ``dtype`` and ``shape`` nil in the header, for a ``None`` array).

``decode`` checks everything against ``schema.yaml`` and raises a ``WireError`` subclass naming the
field and the problem; it never returns a half-valid message. Decoded arrays are zero-copy views
of the received frames (``np.frombuffer``) marked read-only: copy them before modifying. They keep
the frames alive as long as they are referenced.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import msgpack
import numpy as np

from ._values import INT64_MAX, field_value
from .errors import MalformedMessage, MessageTooLarge, UnknownSchema, UnsupportedVersion
from .messages import MESSAGES
from .schema import FieldSpec, MessageSpec, load_schema

DEFAULT_MAX_BYTES = 256 * 2**20  # 256 MiB: a few 4K RGB frames with features; raise it per socket if needed
_SCHEMA = load_schema()
VERSION = _SCHEMA.version
_HEADER_KEYS = tuple(f.name for f in _SCHEMA.header)
_SPEC_BY_NAME: dict[str, MessageSpec] = {m.schema_name: m for m in _SCHEMA.messages.values()}
_SPEC_BY_CLASS: dict[type, MessageSpec] = {cls: _SPEC_BY_NAME[name] for name, cls in MESSAGES.items()}
_WIRE_DTYPES = frozenset(_SCHEMA.dtypes.values())
_DTYPE_ALIASES = {"<u1": "|u1"}  # "<u1" is how a non-numpy writer naturally spells uint8


def _dtype_names(dtypes: Sequence[str]) -> str:
    names = {v: k for k, v in _SCHEMA.dtypes.items()}
    return " or ".join(names[d] for d in dtypes)


def _array_to_wire(spec: FieldSpec, value: Any, where: str) -> np.ndarray | None:
    if value is None:
        if spec.optional:
            return None
        raise ValueError(f"{where}: required array is None (expected {spec.type_text()})")
    array = np.asarray(value)
    if array.dtype.byteorder == ">":  # the wire is little-endian; swap rather than refuse
        array = array.astype(array.dtype.newbyteorder("<"))
    if array.dtype.str not in spec.dtypes:
        raise TypeError(f"{where}: dtype {array.dtype} not allowed, expected {_dtype_names(spec.dtypes)}")
    _check_shape(spec, array.shape, where, ValueError)
    return array


def _check_shape(spec: FieldSpec, shape: Sequence[int], where: str, error: type[Exception]) -> None:
    if len(shape) != len(spec.shape):
        raise error(
            f"{where}: rank {len(shape)} (shape {list(shape)}), schema wants rank {len(spec.shape)} {list(spec.shape)}"
        )
    for axis, (got, want) in enumerate(zip(shape, spec.shape, strict=True)):
        if isinstance(want, int) and got != want:
            raise error(f"{where}: shape {list(shape)}, axis {axis} must be {want} (schema {list(spec.shape)})")


def _common_int(value: Any, where: str, convert: bool) -> int:
    if convert and isinstance(value, np.integer):
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= INT64_MAX:
        message = f"{where}: expected an int in [0, 2**63), got {type(value).__name__} {value!r:.40}"
        raise (TypeError(message) if convert else MalformedMessage(message))
    return value


def encode(msg: Any, topic: str) -> list[bytes]:
    """Frames of ``msg`` on ``topic``: ``[topic utf-8, msgpack header, *one buffer per array field]``.

    Arrays must already have an allowed dtype (big-endian input is byte-swapped, any memory
    layout is written in C order). Raises ``TypeError``/``ValueError`` naming the field for a
    message that does not fit its schema (a sender bug, not a wire error)."""
    spec = _SPEC_BY_CLASS.get(type(msg))
    if spec is None:
        raise TypeError(f"encode: {type(msg).__name__} is not an olsplat_msgs message")
    if not isinstance(topic, str) or not topic:
        raise ValueError(f"encode: topic must be a non-empty str, got {topic!r}")
    if not isinstance(msg.frame_id, str):
        raise TypeError(f"{spec.name}.frame_id: expected str, got {type(msg.frame_id).__name__}")
    header: dict[str, Any] = {
        "schema": spec.schema_name,
        "version": VERSION,
        "stamp_ns": _common_int(msg.stamp_ns, f"{spec.name}.stamp_ns", True),
        "seq": _common_int(msg.seq, f"{spec.name}.seq", True),
        "frame_id": msg.frame_id,
        "fields": {
            f.name: field_value(f, getattr(msg, f.name), f"{spec.name}.{f.name}", True) for f in spec.scalar_fields
        },
    }
    entries: list[dict[str, Any]] = []
    buffers: list[bytes] = []
    for f in spec.array_fields:
        array = _array_to_wire(f, getattr(msg, f.name), f"{spec.name}.{f.name}")
        if array is None:
            entries.append({"name": f.name, "dtype": None, "shape": None})
            buffers.append(b"")
        else:
            entries.append({"name": f.name, "dtype": array.dtype.str, "shape": list(array.shape)})
            buffers.append(array.tobytes(order="C"))
    header["arrays"] = entries
    return [topic.encode("utf-8"), msgpack.packb(header, use_bin_type=True), *buffers]


def _byte_views(frames: Any) -> list[memoryview]:
    try:
        frames = list(frames)
    except TypeError:
        raise MalformedMessage(
            f"frames must be a sequence of bytes-like objects, got {type(frames).__name__}"
        ) from None
    views = []
    for i, frame in enumerate(frames):
        try:
            view = memoryview(frame)
            views.append(view if view.ndim == 1 and view.format == "B" else view.cast("B"))
        except (TypeError, ValueError):
            raise MalformedMessage(f"frame {i}: {type(frame).__name__} is not a contiguous bytes-like object") from None
    return views


def _reject_ext(code: int, data: bytes) -> None:
    raise MalformedMessage(f"header: msgpack extension type {code} is not allowed")


def _unpack_header(view: memoryview) -> dict:
    try:
        header = msgpack.unpackb(view, raw=False, strict_map_key=True, ext_hook=_reject_ext, timestamp=0)
    except MalformedMessage:
        raise
    except Exception as exc:  # msgpack raises several unrelated types for bad input
        raise MalformedMessage(f"header: not a valid msgpack document ({type(exc).__name__}: {exc})") from None
    if not isinstance(header, dict):
        raise MalformedMessage(f"header: expected a msgpack map, got {type(header).__name__}")
    return header


def _array_from_wire(spec: FieldSpec, entry: Any, view: memoryview, where: str) -> np.ndarray | None:
    if not isinstance(entry, dict) or set(entry) != {"name", "dtype", "shape"}:
        raise MalformedMessage(f"{where}: array entry must be a map with keys name, dtype, shape; got {entry!r:.120}")
    if entry["name"] != spec.name:
        raise MalformedMessage(
            f"{where}: array entry named {entry['name']!r:.40}, expected {spec.name!r} (schema order)"
        )
    dtype, shape = entry["dtype"], entry["shape"]
    if dtype is None or shape is None:
        if dtype is not None or shape is not None:
            raise MalformedMessage(
                f"{where}: dtype and shape must both be nil for a None array, got {dtype!r:.40} / {shape!r:.40}"
            )
        if not spec.optional:
            raise MalformedMessage(f"{where}: nil (None), but the array is required")
        if view.nbytes:
            raise MalformedMessage(f"{where}: None array with a {view.nbytes}-byte frame (must be empty)")
        return None
    if not isinstance(dtype, str):
        raise MalformedMessage(f"{where}: dtype must be a string, got {type(dtype).__name__}")
    dtype = _DTYPE_ALIASES.get(dtype, dtype)
    if dtype not in _WIRE_DTYPES:
        raise MalformedMessage(f"{where}: dtype {dtype!r:.20} is not a wire dtype ({', '.join(sorted(_WIRE_DTYPES))})")
    if dtype not in spec.dtypes:
        raise MalformedMessage(f"{where}: dtype {dtype!r} not allowed, expected {_dtype_names(spec.dtypes)}")
    if not isinstance(shape, list) or not all(
        isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= INT64_MAX for s in shape
    ):
        raise MalformedMessage(f"{where}: shape must be a list of non-negative ints, got {shape!r:.80}")
    _check_shape(spec, shape, where, MalformedMessage)
    itemsize = np.dtype(dtype).itemsize
    expected = math.prod(shape) * itemsize
    if expected != view.nbytes:
        raise MalformedMessage(
            f"{where}: frame has {view.nbytes} bytes, dtype {dtype} x shape {shape} needs {expected}"
        )
    array = np.frombuffer(view, dtype=dtype).reshape(shape)
    array.flags.writeable = False  # a view of the receive buffer: writing would corrupt (or fault on) shared memory
    return array


def decode(frames: Sequence[Any], max_bytes: int = DEFAULT_MAX_BYTES) -> tuple[str, Any]:
    """``(topic, message)`` from the frames of one multipart message (bytes-like objects, e.g.
    ``bytes`` or ``zmq.Frame``). Raises ``MessageTooLarge`` when the frames add up to more than
    ``max_bytes``, ``UnknownSchema``/``UnsupportedVersion`` for a message from another schema, and
    ``MalformedMessage`` for anything else that does not match the schema."""
    views = _byte_views(frames)
    total = sum(v.nbytes for v in views)
    if total > max_bytes:
        raise MessageTooLarge(f"message of {total} bytes exceeds max_bytes={max_bytes}")
    if len(views) < 2:
        raise MalformedMessage(f"expected at least 2 frames (topic, header), got {len(views)}")
    try:
        topic = bytes(views[0]).decode("utf-8")
    except UnicodeDecodeError:
        raise MalformedMessage(f"frame 0 (topic) is not UTF-8: {bytes(views[0][:40])!r}") from None
    if not topic:
        raise MalformedMessage("frame 0 (topic) is empty")
    header = _unpack_header(views[1])
    name = header.get("schema")
    if not isinstance(name, str):
        raise MalformedMessage(f"header: 'schema' must be a string, got {name!r:.40}")
    spec = _SPEC_BY_NAME.get(name)
    if spec is None:
        raise UnknownSchema(f"unknown schema {name!r:.80}; this receiver knows {', '.join(_SPEC_BY_NAME)}")
    version = header.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise MalformedMessage(f"{spec.name} header: 'version' must be an int, got {version!r:.40}")
    if version != VERSION:
        raise UnsupportedVersion(f"{spec.name}: schema version {version}, this receiver speaks version {VERSION}")
    if set(header) != set(_HEADER_KEYS):
        missing, extra = sorted(set(_HEADER_KEYS) - set(header)), sorted(set(header) - set(_HEADER_KEYS))
        raise MalformedMessage(f"{spec.name} header: missing keys {missing}, unexpected keys {extra}")
    expected_frames = 2 + len(spec.array_fields)
    if len(views) != expected_frames:
        raise MalformedMessage(
            f"{spec.name}: expected {expected_frames} frames (topic, header, {len(spec.array_fields)} arrays), "
            f"got {len(views)}"
        )
    values: dict[str, Any] = {
        "stamp_ns": _common_int(header["stamp_ns"], f"{spec.name}.stamp_ns", False),
        "seq": _common_int(header["seq"], f"{spec.name}.seq", False),
    }
    if not isinstance(header["frame_id"], str):
        raise MalformedMessage(f"{spec.name}.frame_id: expected str, got {type(header['frame_id']).__name__}")
    values["frame_id"] = header["frame_id"]
    fields = header["fields"]
    if not isinstance(fields, dict):
        raise MalformedMessage(f"{spec.name} header: 'fields' must be a map, got {type(fields).__name__}")
    wanted = {f.name for f in spec.scalar_fields}
    if set(fields) != wanted:
        missing, extra = sorted(wanted - set(fields)), sorted(set(fields) - wanted)
        raise MalformedMessage(f"{spec.name}: missing fields {missing}, unexpected fields {extra}")
    for f in spec.scalar_fields:
        values[f.name] = field_value(f, fields[f.name], f"{spec.name}.{f.name}", False)
    entries = header["arrays"]
    if not isinstance(entries, list) or len(entries) != len(spec.array_fields):
        raise MalformedMessage(
            f"{spec.name} header: 'arrays' must list {len(spec.array_fields)} entries, got {entries!r:.120}"
        )
    for i, (f, entry) in enumerate(zip(spec.array_fields, entries, strict=True)):
        values[f.name] = _array_from_wire(f, entry, views[2 + i], f"{spec.name}.{f.name}")
    return topic, MESSAGES[name](**values)
