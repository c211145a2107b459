"""The query server before any map exists: an explicit "no_map" at once (not a hang), for a query
with and without a view; a StatusRequest works before any map; and once a snapshot appears
(the refiner's latest.json), the same server answers from it without a restart."""

from __future__ import annotations

import shutil
import time

import pytest

from olsplat_msgs import MapUpdated, QueryReply, QueryRequest, StatusReply, StatusRequest
from olsplat_nodes.nodes.query_server import QueryServerNode
from olsplat_nodes.transport import QueryClient

from .conftest import ENCODE_VIEW, NodeThread, every, raw_socket, send_msg, wait_for

pytestmark = pytest.mark.timeout(120)


def test_no_map_yet_is_answered_at_once_and_status_works(ctx, sockdir, tiny, tiny_run, tmp_path):
    import zmq

    scene, _ = tiny
    endpoint = f"ipc://{sockdir}/query.sock"
    maps = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/map.sock", bind=True)
    node = QueryServerNode(
        "query_server",
        {
            "map": str(scene / "map" / "point_cloud.ply"),
            "map_dir": str(tmp_path / "map"),
            "views": str(tmp_path / "views"),
            "query_endpoint": endpoint,
            "diagnostics_bind": f"ipc://{sockdir}/diagnostics.sock",
            "map_in": f"ipc://{sockdir}/map.sock",
        },
    )
    try:
        with NodeThread(node) as running, QueryClient(ctx, endpoint, timeout_s=10.0) as client:
            status = client.request(StatusRequest(request_id="s1"))  # also waits for the node to be up
            assert isinstance(status, StatusReply) and status.request_id == "s1" and status.map_version == 0
            assert status.nodes[0]["node"] == "query_server" and status.nodes[0]["level"] == 0
            assert "map version 0" in status.nodes[0]["message"]

            client.timeout_s = 2.0  # "at once": a hang would raise NoReply
            for view in ("", ENCODE_VIEW):
                start = time.monotonic()
                reply = client.request(
                    QueryRequest(request_id=f"q-{view}", text="red roof buildings", view=view, heatmap=bool(view))
                )
                elapsed = time.monotonic() - start
                assert isinstance(reply, QueryReply) and reply.request_id == f"q-{view}"
                assert reply.status == "no_map" and "no map yet" in reply.message and elapsed < 1.0
                assert reply.map_version == 0 and reply.view == view and reply.instances == []
                assert reply.heatmap is None and reply.mask is None and reply.image is None

            # the refiner writes its first snapshot and announces it: answered from it, no restart
            shutil.copytree(tiny_run / "views", tmp_path / "views")
            shutil.copytree(tiny_run / "map", tmp_path / "staging")
            (tmp_path / "staging").rename(tmp_path / "map")  # appears at once, as the refiner's atomic writes do
            wait_for(
                lambda: client.request(StatusRequest()).map_version == 1,
                10,
                "the first map to be loaded",
                step=every(
                    0.2, lambda: send_msg(maps, MapUpdated(version=1, path=str(tmp_path / "map"), views=1), "map")
                ),
            )
            client.timeout_s = 30.0
            reply = client.request(
                QueryRequest(request_id="q", text="red roof buildings", view=ENCODE_VIEW, heatmap=True)
            )
            assert reply.status == "ok" and reply.map_version == 1 and reply.heatmap.shape == (240, 320)
            running.assert_running()
    finally:
        maps.close()
