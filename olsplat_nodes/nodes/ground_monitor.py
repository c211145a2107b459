"""ground_monitor: the ground station's side of a launch (client only). Every ``period_s`` it asks
the drone's query server for the graph's status over the ground link (CURVE when keys are
given), logs one line per node and writes the latest answer to ``status_file``. A silent
link is logged and retried; it never ends the ground launch."""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from pathlib import Path

from olsplat_msgs import StatusRequest

from ..transport import NoReply, QueryClient, curve
from ..transport.diagnostics import LEVEL_NAMES
from .base import Node

log = logging.getLogger(__name__)


class GroundMonitorNode(Node):
    DEFAULTS = {
        "connect": "tcp://127.0.0.1:5600",
        "period_s": 5.0,
        "timeout_s": 5.0,
        "client_secret": "",  # CURVE: this client's secret key file ("" = plain link)
        "server_public": "",  # CURVE: the drone's public key file
        "status_file": "{run_dir}/ground_status.json",
    }

    def run(self, stop: threading.Event) -> int:
        p = self.params
        keys = curve.ClientKeys(p["client_secret"], p["server_public"]) if p["client_secret"] else None
        client = QueryClient(self.context, p["connect"], timeout_s=p["timeout_s"], keys=keys)
        try:
            while not stop.is_set():
                try:
                    reply = client.request(StatusRequest(request_id=uuid.uuid4().hex[:12]))
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
                    path = Path(p["status_file"])
                    tmp = path.with_name(path.name + ".tmp")
                    tmp.write_text(
                        json.dumps(
                            {"time": time.time(), "map_version": reply.map_version, "nodes": reply.nodes}, default=str
                        )
                    )
                    tmp.replace(path)
                stop.wait(p["period_s"])
            return 130
        finally:
            client.close()
