"""ZeroMQ transport of the node graph: streams (PUB/SUB with drop and gap counting), the query
link (ROUTER/DEALER with timeouts, optional CURVE), and heartbeats. Messages are encoded with
``olsplat_msgs``; bad input on any socket is counted, logged and dropped, never raised.
The wire format is specified in msgs/README.md. Like the ZeroMQ sockets they wrap, these objects
belong to one thread each (a composed launch gives every node its own)."""

from . import curve
from .diagnostics import DIAGNOSTICS_TOPIC, Diagnostics, DiagnosticsCollector
from .limits import CONTROL_MAX_BYTES, REQUEST_MAX_BYTES
from .pubsub import Publisher, Subscriber
from .query import QUERY_TOPIC, NoReply, QueryClient, QueryServer

__all__ = [
    "CONTROL_MAX_BYTES",
    "DIAGNOSTICS_TOPIC",
    "QUERY_TOPIC",
    "REQUEST_MAX_BYTES",
    "Diagnostics",
    "DiagnosticsCollector",
    "NoReply",
    "Publisher",
    "QueryClient",
    "QueryServer",
    "Subscriber",
    "curve",
]
