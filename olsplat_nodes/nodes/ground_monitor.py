"""ground_monitor: the ground station's side of a launch (client only). Every ``period_s`` it asks
the drone's query server for the graph's status over the ground link (CURVE when keys are
given), logs one line per node and writes the latest answer to ``status_file``. A silent
link is logged and retried; it never ends the ground launch."""

from __future__ import annotations

import json
import logging
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from olsplat_msgs import StatusRequest

from ..transport import NoReply, QueryClient, curve
from ..transport.diagnostics import LEVEL_NAMES
from .base import Node

log = logging.getLogger(__name__)


class GroundMonitorNode(Node):
    @dataclass(frozen=True)
    class Params:
        connect: str = "tcp://127.0.0.1:5600"
        period_s: float = 5.0
        timeout_s: float = 5.0
        client_secret: str = ""  # CURVE: this client's secret key file ("" = plain link)
        server_public: str = ""  # CURVE: the drone's public key file
        status_file: str = "{run_dir}/ground_status.json"

    def setup(self) -> None:
        p = self.params
        keys = curve.ClientKeys(p.client_secret, p.server_public) if p.client_secret else None
        self.client = self.own(QueryClient(self.context, p.connect, timeout_s=p.timeout_s, keys=keys))

    def spin(self) -> int | None:
        try:
            reply = self.client.request(StatusRequest(request_id=uuid.uuid4().hex[:12]))
        except NoReply as exc:
            log.warning("%s", exc)
        else:
            for node in reply.nodes:
                v = node["values"]
                log.info(
                    "%-16s %-5s rate %.2f Hz latency %.0f ms drops %d",
                    node["node"],
                    LEVEL_NAMES.get(node["level"], node["level"]),
                    v.get("rate_hz", 0.0),
                    v.get("latency_ms", 0.0),
                    int(v.get("dropped", 0)) + int(v.get("gaps", 0)),
                )
            path = Path(self.params.status_file)
            tmp = path.with_name(path.name + ".tmp")
            status = {"time": time.time(), "map_version": reply.map_version, "nodes": reply.nodes}
            tmp.write_text(json.dumps(status, default=str))
            tmp.replace(path)
        self.stop.wait(self.params.period_s)
        return None
