"""A hostile client floods the query link with 100 queries per second for 10 s: it is told
"busy" beyond its rate limit, an honest client is still answered as fast as before, and the
server's memory stays flat. CURVE on, as on a drone: clients are told apart by their keys."""

from __future__ import annotations

import resource
import shutil
import threading
import time

import numpy as np
import pytest
import zmq

from olsplat_msgs import QueryRequest
from olsplat_nodes.transport import QueryClient, curve
from tests.helpers import free_port

from .conftest import NodeThread, query_server

pytestmark = pytest.mark.timeout(180)


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def test_a_flooding_client_is_told_busy_and_others_are_served(ctx, sockdir, tiny, tiny_run, tmp_path):
    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")
    _, server_secret = curve.generate(tmp_path / "server", "server")
    server_public = tmp_path / "server" / "server.key"
    (tmp_path / "allow").mkdir()
    keys = {}
    for name in ("honest", "flood"):
        public, secret = curve.generate(tmp_path / name, name)
        shutil.copy(public, tmp_path / "allow")
        keys[name] = curve.ClientKeys(secret, server_public)
    endpoint = f"tcp://127.0.0.1:{free_port()}"
    node = query_server(
        scene,
        sockdir,
        tmp_path / "map",
        tmp_path / "views",
        query_endpoint=endpoint,
        server_secret=str(server_secret),
        allow_dir=str(tmp_path / "allow"),
    )

    def timed(client, text="red roof buildings"):
        start = time.perf_counter()
        reply = client.request(QueryRequest(text=text, negatives=["road", "trees"]))
        return reply, time.perf_counter() - start

    with NodeThread(node) as running, QueryClient(ctx, endpoint, timeout_s=30.0, keys=keys["honest"]) as honest:
        timed(honest)  # warm: the first query loads the encoder
        before = []
        for _ in range(10):
            reply, seconds = timed(honest)
            assert reply.status == "ok", reply.message
            before.append(seconds)
            time.sleep(0.25)
        rss_before = _rss_mb()

        statuses: list[str] = []
        stop = threading.Event()

        def flood():
            with QueryClient(zmq.Context.instance(), endpoint, timeout_s=30.0, keys=keys["flood"]) as client:
                next_at = time.monotonic()
                while not stop.is_set():
                    statuses.append(timed(client, "road")[0].status)
                    next_at += 0.01  # 100 per second, as long as the server keeps up
                    time.sleep(max(0.0, next_at - time.monotonic()))

        flooder = threading.Thread(target=flood, daemon=True)
        flooder.start()
        during = []
        end = time.monotonic() + 10.0
        while time.monotonic() < end:
            reply, seconds = timed(honest)
            assert reply.status == "ok", reply.message  # never "busy": the limit is per client
            during.append(seconds)
            time.sleep(0.25)
        stop.set()
        flooder.join(30)
        running.assert_running()
        rss_after = _rss_mb()

    assert len(statuses) >= 500, len(statuses)  # the flood did reach ~100 queries per second
    busy = statuses.count("busy")
    assert busy >= 0.8 * len(statuses) and statuses.count("ok") <= 10 + 5 * 11, (busy, len(statuses))
    p95_before, p95_during = np.percentile(before, 95), np.percentile(during, 95)
    assert p95_during <= 2 * p95_before + 0.05, (p95_before, p95_during)
    assert rss_after - rss_before < 50, (rss_before, rss_after)
