"""olsplat_msgs: the wire schema of the node graph and its codec (no zmq here).

``schema.yaml`` is the single source; ``msgs/README.md`` is the wire specification for writing
a client in another language. ``encode(msg, topic)`` gives ``[topic, msgpack header, *array
buffers]``; ``decode(frames, max_bytes)`` gives ``(topic, msg)`` or raises a ``WireError``.
Decoded arrays are read-only zero-copy views of the received frames. Records inside fields
(``QueryReply.instances``: ``Instance3D``/``Instance2D``) are plain dicts checked key by key.
"""

from .codec import DEFAULT_MAX_BYTES, VERSION, decode, encode
from .errors import MalformedMessage, MessageTooLarge, UnknownSchema, UnsupportedVersion, WireError
from .messages import (
    MESSAGES,
    DiagnosticStatus,
    EndOfStream,
    ImageFrame,
    Instance,
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
from .schema import load_schema

__all__ = [
    "DEFAULT_MAX_BYTES",
    "MESSAGES",
    "VERSION",
    "DiagnosticStatus",
    "EndOfStream",
    "ImageFrame",
    "Instance",
    "Instance2D",
    "Instance3D",
    "MalformedMessage",
    "MapUpdated",
    "MessageTooLarge",
    "ObservationsAdded",
    "QueryReply",
    "QueryRequest",
    "RegionFeatures",
    "SplatsReply",
    "SplatsRequest",
    "StatusReply",
    "StatusRequest",
    "UnknownSchema",
    "UnsupportedVersion",
    "ViewPose",
    "ViewsReply",
    "ViewsRequest",
    "WireError",
    "decode",
    "encode",
    "load_schema",
]
