"""Structure-aware fuzzing of a running graph (``test_live_fuzz.py``; ``make fuzz`` runs it longer).

Three parts:
- ``Mutator``: mutants of valid encoded messages, made by 1-3 random operators that know the
  wire layout (``msgs/README.md``): the msgpack header's keys, field values and array
  descriptions; the array frames (truncated, extended, dropped, swapped); the array values
  (NaN, infinities, out-of-range labels and counts, a wrong feature width, a photo of another
  size, a pose that is not rigid); another message type on the topic; raw garbage.
- ``Oracle``: whether the receiving node must refuse a mutant, decided with the same functions
  the node uses (``decode`` with the socket's size limit, the node's accepted types, and
  ``camera_of`` / ``view_of`` for frames and views). A mutant the node would take as a valid
  message is not sent: it would change the flight (a view of its own, an early end of stream).
- ``GateProxy``: sits on one link of the graph (the downstream nodes connect to it instead of
  to the upstream node), forwards the real traffic, holds it while the fuzzer runs, and sends
  the fuzzer's messages. It publishes with ``XPUB_NODROP``: a full queue makes it wait instead
  of dropping, so every mutant reaches the node and can be counted there.
"""

from __future__ import annotations

import copy
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import zmq

from olsplat_msgs import WireError, decode

HOSTILE_VALUES: list[Any] = [
    None, -1, 0, 2**63, -(2**63), 2**64 - 1, 1e308, -1e308, math.nan, math.inf, True, "", "x" * 70_000,
    "\udcff".encode("utf-8", "surrogatepass").decode("utf-8", "replace"), [], [1, 2, 3], {}, {"a": 1}, b"\x00\xff",
]  # fmt: skip
OTHER_DTYPES = ["<f4", "<f8", "<f2", "|u1", "<i4", "<i8", "|b1", "<U4", "|O", ">f4", "<c8", "", 7]
SCHEMAS = [
    "olsplat_msgs/ImageFrame", "olsplat_msgs/RegionFeatures", "olsplat_msgs/ObservationsAdded",
    "olsplat_msgs/MapUpdated", "olsplat_msgs/EndOfStream", "olsplat_msgs/DiagnosticStatus",
    "olsplat_msgs/QueryRequest", "olsplat_msgs/QueryReply", "olsplat_msgs/StatusRequest",
    "olsplat_msgs/NoSuchMessage", "", "olsplat_msgs/",
]  # fmt: skip


class Mutator:
    """Mutants of ``templates`` (encoded messages, ``[topic, header, *arrays]``); ``foreign`` are
    valid messages of other types, sent on the templates' topic."""

    def __init__(self, templates: list[list[bytes]], foreign: list[list[bytes]], seed: int):
        self.templates, self.foreign = templates, foreign
        self.rng = np.random.default_rng(seed)
        self.operators: list[Callable[[bytes, dict, list[bytes]], tuple[dict | bytes, list[bytes]]]] = [
            self._drop_key, self._hostile_key, self._version, self._schema, self._drop_field,
            self._hostile_field, self._extra_field, self._array_dtype, self._array_shape, self._drop_array_doc,
            self._truncate_frame, self._extend_frame, self._drop_frame, self._swap_frames, self._nan_values,
            self._int_values, self._narrow_features, self._resize_image, self._scale_pose, self._size_fields,
        ]  # fmt: skip

    def __call__(self) -> list[bytes]:
        rng = self.rng
        draw = rng.random()
        if draw < 0.03:  # raw garbage after the topic
            topic = self.templates[0][0]
            return [topic, *[rng.bytes(int(rng.integers(0, 400))) for _ in range(int(rng.integers(0, 4)))]]
        if draw < 0.08 and self.foreign:  # a valid message of another type on this topic
            foreign = self.foreign[int(rng.integers(len(self.foreign)))]
            return [self.templates[0][0], *foreign[1:]]
        topic, header, *arrays = self.templates[int(rng.integers(len(self.templates)))]
        doc: dict | bytes = msgpack.unpackb(header, raw=False)
        for _ in range(int(rng.integers(1, 4))):
            if not isinstance(doc, dict):
                break
            operator = self.operators[int(rng.integers(len(self.operators)))]
            try:
                with np.errstate(all="ignore"):  # NaN times a number is the point, not a warning
                    doc, arrays = operator(topic, doc, list(arrays))
            except (TypeError, ValueError, OverflowError):  # an earlier operator made it inapplicable
                continue
        try:
            packed = doc if isinstance(doc, bytes) else msgpack.packb(doc, use_bin_type=True)
        except (ValueError, OverflowError, TypeError):  # not representable in msgpack: garbage instead
            packed = rng.bytes(int(rng.integers(1, 200)))
        if rng.random() < 0.05:  # a byte or two of the header flipped
            flipped = bytearray(packed)
            for _ in range(int(rng.integers(1, 3))):
                if flipped:
                    flipped[int(rng.integers(len(flipped)))] ^= int(rng.integers(1, 256))
            packed = bytes(flipped)
        return [topic, packed, *arrays]

    # --- the header --------------------------------------------------------------------------
    def _hostile(self):
        return copy.deepcopy(self._pick(HOSTILE_VALUES))  # a fresh [] or {}: never shared between mutants

    def _pick(self, items):
        return items[int(self.rng.integers(len(items)))] if items else None

    def _drop_key(self, topic, doc, arrays):
        key = self._pick(list(doc))
        doc.pop(key, None)
        return doc, arrays

    def _hostile_key(self, topic, doc, arrays):
        doc[self._pick(list(doc) or ["seq"])] = self._hostile()
        return doc, arrays

    def _version(self, topic, doc, arrays):
        doc["version"] = self._pick([0, 2, 99, -1, "1", 1.0, None])
        return doc, arrays

    def _schema(self, topic, doc, arrays):
        doc["schema"] = self._pick(SCHEMAS)
        return doc, arrays

    def _drop_field(self, topic, doc, arrays):
        fields = doc.get("fields")
        if isinstance(fields, dict) and fields:
            fields.pop(self._pick(list(fields)))
        return doc, arrays

    def _hostile_field(self, topic, doc, arrays):
        fields = doc.get("fields")
        if isinstance(fields, dict) and fields:
            fields[self._pick(list(fields))] = self._hostile()
        return doc, arrays

    def _extra_field(self, topic, doc, arrays):
        if isinstance(doc.get("fields"), dict):
            doc["fields"][self._pick(["surplus", "name2", "x" * 300])] = self._hostile()
        return doc, arrays

    def _array_doc(self, doc):
        entries = doc.get("arrays")
        return self._pick(entries) if isinstance(entries, list) and entries else None

    def _array_dtype(self, topic, doc, arrays):
        entry = self._array_doc(doc)
        if isinstance(entry, dict):
            entry["dtype"] = self._pick(OTHER_DTYPES)
        return doc, arrays

    def _array_shape(self, topic, doc, arrays):
        entry = self._array_doc(doc)
        if isinstance(entry, dict) and isinstance(entry.get("shape"), list):
            shape = list(entry["shape"])
            choice = int(self.rng.integers(6))
            if choice == 0:
                shape.append(int(self.rng.integers(1, 4)))
            elif choice == 1 and shape:
                shape.pop()
            elif choice == 2 and shape:
                shape[int(self.rng.integers(len(shape)))] *= 2
            elif choice == 3 and shape:
                shape[int(self.rng.integers(len(shape)))] = self._pick([0, -1, 2**40, 2**62, 2**64 - 1])
            elif choice == 4:
                shape = self._pick([None, "3", [1.5], [[2]], {}])
            else:
                shape = shape[::-1]
            entry["shape"] = shape
        return doc, arrays

    def _drop_array_doc(self, topic, doc, arrays):
        entries = doc.get("arrays")
        if isinstance(entries, list) and entries:
            entries.pop(int(self.rng.integers(len(entries))))
        return doc, arrays

    # --- the array frames --------------------------------------------------------------------
    def _truncate_frame(self, topic, doc, arrays):
        if arrays:
            i = int(self.rng.integers(len(arrays)))
            arrays[i] = arrays[i][: int(self.rng.integers(0, max(1, len(arrays[i]))))]
        return doc, arrays

    def _extend_frame(self, topic, doc, arrays):
        if arrays:
            i = int(self.rng.integers(len(arrays)))
            arrays[i] = arrays[i] + self.rng.bytes(int(self.rng.integers(1, 64)))
        else:
            arrays.append(self.rng.bytes(16))
        return doc, arrays

    def _drop_frame(self, topic, doc, arrays):
        if arrays:
            arrays.pop(int(self.rng.integers(len(arrays))))
        return doc, arrays

    def _swap_frames(self, topic, doc, arrays):
        if len(arrays) >= 2:
            i, j = self.rng.choice(len(arrays), 2, replace=False)
            arrays[i], arrays[j] = arrays[j], arrays[i]
        return doc, arrays

    # --- array values (the message still decodes; its content is wrong) -----------------------
    def _decoded(self, doc, arrays, name):
        """(index, numpy copy) of the array field ``name``, or None."""
        entries = doc.get("arrays")
        if not isinstance(entries, list) or len(entries) != len(arrays):
            return None
        for i, entry in enumerate(entries):
            if isinstance(entry, dict) and entry.get("name") == name:
                try:
                    dtype, shape = np.dtype(entry["dtype"]), tuple(entry["shape"])
                    return i, np.frombuffer(arrays[i], dtype).reshape(shape).copy()
                except (TypeError, ValueError, KeyError):
                    return None
        return None

    def _put(self, doc, arrays, i, value):
        arrays[i] = np.ascontiguousarray(value).tobytes()
        doc["arrays"][i]["shape"] = list(value.shape)

    def _nan_values(self, topic, doc, arrays):
        name = self._pick(["features", "K", "world_from_camera", "D"])
        found = self._decoded(doc, arrays, name)
        if found is not None and found[1].size and found[1].dtype.kind == "f":
            i, value = found
            value.reshape(-1)[int(self.rng.integers(value.size))] = self._pick([np.nan, np.inf, -np.inf])
            self._put(doc, arrays, i, value)
        return doc, arrays

    def _int_values(self, topic, doc, arrays):
        name = self._pick(["label_maps", "level_sizes"])
        found = self._decoded(doc, arrays, name)
        if found is not None and found[1].size:
            i, value = found
            value.reshape(-1)[int(self.rng.integers(value.size))] = self._pick([-5, 2**31 - 1, 10_000, -(2**31)])
            self._put(doc, arrays, i, value)
        return doc, arrays

    def _narrow_features(self, topic, doc, arrays):
        found = self._decoded(doc, arrays, "features")
        if found is not None and found[1].ndim == 2 and found[1].shape[1] > 1:
            i, value = found
            self._put(doc, arrays, i, value[:, : value.shape[1] // 2])
        return doc, arrays

    def _resize_image(self, topic, doc, arrays):
        found = self._decoded(doc, arrays, "image")
        if found is not None and found[1].ndim == 3 and found[1].shape[0] > 2:
            i, value = found
            self._put(doc, arrays, i, value[: value.shape[0] // 2])
        return doc, arrays

    def _scale_pose(self, topic, doc, arrays):
        found = self._decoded(doc, arrays, "world_from_camera")
        if found is not None and found[1].shape == (4, 4):
            i, value = found
            value[:3, :3] *= self._pick([2.0, 0.5, -1.0, 0.0])
            if value[0, 0] < 0:  # -1 keeps the rows orthonormal but flips handedness: not a rotation
                value[:3, 0] *= -1.0
                value[:3, :3] *= -1.0
            self._put(doc, arrays, i, value)
        return doc, arrays

    def _size_fields(self, topic, doc, arrays):
        fields = doc.get("fields")
        if isinstance(fields, dict) and "width" in fields:
            fields[self._pick(["width", "height"])] = self._pick([0, 1, -3, 7, 2**31])
        return doc, arrays


class Oracle:
    """Whether the node behind a socket must refuse (and count) a message: it does not decode
    within ``max_bytes``, or its type is not one the node takes, or ``checks[type]`` raises
    ValueError. ``checks[type] = None``: any decodable message of that type is valid."""

    def __init__(self, checks: dict[type, Callable[[Any], Any] | None], max_bytes: int):
        self.checks, self.max_bytes = checks, max_bytes

    def refused(self, frames: list[bytes]) -> bool:
        try:
            _, message = decode(frames, max_bytes=self.max_bytes)
        except WireError:
            return True
        if type(message) not in self.checks:
            return True
        check = self.checks[type(message)]
        if check is None:
            return False
        try:
            check(message)
        except ValueError:
            return True
        return False


def bad_messages(mutator: Mutator, oracle: Oracle, count: int) -> tuple[list[list[bytes]], int]:
    """``count`` mutants the oracle says must be refused, and how many valid ones were skipped."""
    chosen, skipped = [], 0
    while len(chosen) < count:
        frames = mutator()
        if oracle.refused(frames):
            chosen.append(frames)
        else:
            skipped += 1
    return chosen, skipped


class GateProxy:
    """One link of the graph through the test: SUB on the upstream node's bound endpoint, XPUB
    (no drop) bound where the downstream nodes connect. Real messages are held while ``hold``
    is set and forwarded after, in order; ``inject`` sends a message now."""

    def __init__(self, ctx: zmq.Context, upstream: str, downstream: str):
        self.sub = ctx.socket(zmq.SUB)
        self.sub.linger = 0
        self.sub.rcvhwm = 100_000
        self.sub.setsockopt(zmq.SUBSCRIBE, b"")
        self.sub.connect(upstream)
        self.pub = ctx.socket(zmq.XPUB)
        self.pub.linger = 0
        self.pub.sndhwm = 256
        self.pub.setsockopt(zmq.XPUB_NODROP, 1)
        self.pub.bind(downstream)
        self.hold = True
        self.held: list[list[zmq.Frame]] = []
        self.subscribers = 0
        self.forwarded = self.injected = 0
        self.outbox: queue.Queue[list[bytes]] = queue.Queue(maxsize=64)
        self.stopping = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def inject(self, frames: list[bytes]) -> None:
        self.outbox.put(frames, timeout=120)

    def wait_sent(self, timeout_s: float = 120) -> None:
        deadline = time.monotonic() + timeout_s
        while self.outbox.unfinished_tasks:
            if time.monotonic() > deadline or self.error is not None:
                raise AssertionError(f"proxy: {self.outbox.unfinished_tasks} messages not sent ({self.error})")
            time.sleep(0.01)

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(10)
        self.sub.close()
        self.pub.close()

    def _run(self) -> None:
        try:
            while not self.stopping.is_set():
                self._pump(10)
                while True:
                    try:
                        frames = self.outbox.get_nowait()
                    except queue.Empty:
                        break
                    self._send(frames)
                    self.injected += 1
                    self.outbox.task_done()
                if not self.hold and self.held:
                    for frames in self.held:
                        self._send(frames)
                        self.forwarded += 1
                    self.held = []
        except BaseException as exc:  # reported by wait_sent and the test
            self.error = exc

    def _pump(self, timeout_ms: int) -> None:
        """Take what the upstream node published (held or forwarded) and the subscriptions."""
        while self.pub.poll(0):
            event = self.pub.recv()
            self.subscribers += 1 if event[:1] == b"\x01" else -1 if event[:1] == b"\x00" else 0
        if self.sub.poll(timeout_ms):
            while self.sub.poll(0):
                frames = self.sub.recv_multipart(copy=False)
                if self.hold or self.held:
                    self.held.append(frames)
                else:
                    self._send(frames)
                    self.forwarded += 1

    def _send(self, frames) -> None:
        while True:
            try:
                self.pub.send_multipart(frames, flags=zmq.NOBLOCK, copy=False)
                return
            except zmq.Again:  # a subscriber's queue is full: wait for it, keep reading upstream
                if self.stopping.is_set():
                    return
                self._pump(1)
