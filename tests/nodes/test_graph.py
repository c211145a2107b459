"""The whole graph on the tiny preset, as separate processes over real ZeroMQ sockets:
every frame is aggregated exactly once (also when a node is killed with SIGKILL mid-flight),
the launch ends by itself once the final map is written, and the query server answers."""

from __future__ import annotations

import json
import os
import signal
import threading

import pytest
import zmq

from olsplat_msgs import QueryRequest, StatusRequest
from olsplat_nodes.launcher import Supervisor
from olsplat_nodes.method import read_manifest
from olsplat_nodes.storage import ObservationStore, latest_map
from olsplat_nodes.transport import NoReply, QueryClient
from tests.helpers import free_port, wait_for

from .conftest import Background, fly_and_kill, launch_tiny, pid_of


def _try(client, request):
    try:
        return client.request(request)
    except NoReply:
        return None


@pytest.mark.timeout(600)
def test_graph_aggregates_every_frame_once_survives_kill9_and_answers(tiny, tmp_path):
    scene, summary = tiny
    port = free_port()
    run_dir = tmp_path / "run"
    supervisor = Supervisor(launch_tiny(scene, run_dir, port))
    running = Background(supervisor)
    client = QueryClient(zmq.Context.instance(), f"tcp://127.0.0.1:{port}", timeout_s=20.0)
    try:
        # before any map: an explicit answer, not a hang
        early = wait_for(lambda: _try(client, QueryRequest(request_id="early", text="road")), 60, "the query server")
        assert early.status in ("no_map", "ok")
        # kill -9 the accumulator once it has stored a view or two
        store = run_dir / "store" / "views"
        wait_for(lambda: store.is_dir() and len(list(store.iterdir())) >= 2, 240, "two stored views")
        victim = pid_of(supervisor, "accumulator")
        assert victim, "the supervisor reports the accumulator's pid"
        os.kill(victim, signal.SIGKILL)
        wait_for(lambda: running.code is not None, 480, "the launch to end after the final map")
    finally:
        client.close()
        supervisor.request_stop()
        running.thread.join(30)
    assert running.code == 0
    log = (run_dir / "logs" / "launch.log").read_text()
    assert "accumulator" in log and "restarting" in log  # the kill was seen and the node restarted
    names = ObservationStore(run_dir / "store", 1).names()
    assert sorted(names) == sorted(set(names)) and len(names) == summary["views"]  # every frame, once
    record = latest_map(run_dir / "map")
    assert record["final"] and record["views"] == summary["views"]

    # a query server started after the flight (late joiner) answers from the snapshot on disk
    from olsplat_nodes.nodes.query_server import QueryServerNode

    port2 = free_port()
    node = QueryServerNode(
        "late",
        {
            "map": str(scene / "map" / "point_cloud.ply"),
            "map_dir": str(run_dir / "map"),
            "views": str(run_dir / "views"),
            "query_endpoint": f"tcp://127.0.0.1:{port2}",
            "diagnostics_bind": f"ipc://{tmp_path}/d.sock",
            "map_in": f"ipc://{tmp_path}/m.sock",
        },
    )
    stop = threading.Event()
    thread = threading.Thread(target=node.run, args=(stop,), daemon=True)
    thread.start()
    late = QueryClient(zmq.Context.instance(), f"tcp://127.0.0.1:{port2}", timeout_s=60.0)
    try:
        reply = late.request(
            QueryRequest(
                request_id="q1",
                text="red roof buildings",
                view="frame_0001.jpg",  # its annotation has a red roof (frame_0003's has none)
                heatmap=True,
                threshold=float("nan"),
                negatives=["road", "trees", "lawn"],
            )
        )
        assert reply.status == "ok", reply.message
        assert reply.map_version == record["version"] and reply.request_id == "q1"
        assert reply.heatmap.shape == reply.mask.shape == (240, 320) and reply.image.shape == (240, 320, 3)
        assert reply.mask.any() and any(i["kind"] == "3d" for i in reply.instances)
        empty = late.request(QueryRequest(request_id="q2", text="   "))
        assert empty.status == "bad_request" and "empty" in empty.message
        status = late.request(StatusRequest(request_id="s"))
        assert status.map_version == record["version"] and status.nodes[0]["node"] == "late"
    finally:
        late.close()
        stop.set()
        thread.join(10)


@pytest.mark.timeout(600)
def test_a_recorded_session_replays_through_the_graph_composed_in_one_process(tiny, tmp_path):
    """``olsplat record`` saves a session (here: 8 frames of the tiny flight) to a replay log;
    the graph, as threads of one process (inproc endpoints, one zmq context), aggregates every
    recorded frame from it."""
    from olsplat_nodes.cli import main

    scene, _ = tiny
    log = tmp_path / "session.mcap"
    assert main(["record", "--source", str(scene / "replay.mcap"), "--out", str(log), "--frames", "8"]) == 0
    run_dir = tmp_path / "run"
    overrides = ("launch.compose=true", f"ingest.source={log}", "accumulator.tau_d=0.3", "accumulator.beta=[1, 2]")
    config = launch_tiny(scene, run_dir, free_port(), *overrides)
    assert Supervisor(config).run() == 0
    record = latest_map(run_dir / "map")
    assert record["final"] and record["views"] == 8
    assert len(ObservationStore(run_dir / "store", 1).names()) == 8
    # the method's settings given at launch are the ones the store was made and refined with
    manifest = json.loads((run_dir / "store" / "manifest.json").read_text())
    assert manifest["method"]["name"] == "outlangsplat" and manifest["encoder"] == record["encoder"]
    assert manifest["method"]["aggregation"]["tau_d"] == 0.3 and manifest["method"]["aggregation"]["beta"] == [1, 2]
    assert read_manifest(run_dir / "store").method.aggregation.tau_d == 0.3


@pytest.mark.timeout(600)
def test_the_streamed_map_equals_the_offline_map(tiny, tmp_path):
    """The graph (regions of the finest level only, one thread per node, passes as views arrive)
    and ``olsplat aggregate`` (every level cached, one pass at the end) give the same map for the
    same views, to the bit."""
    import shutil

    import numpy as np

    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.method import named_method
    from olsplat_nodes.pipeline import Scene, aggregate_scene
    from olsplat_nodes.storage import LanguageMap

    scene, _ = tiny
    run_dir = tmp_path / "run"
    assert Supervisor(launch_tiny(scene, run_dir, free_port(), "launch.compose=true")).run() == 0
    streamed = LanguageMap.load(latest_map(run_dir / "map")["path"])
    copy = tmp_path / "scene"
    shutil.copytree(scene, copy)
    aggregate_scene(Scene.open(copy), named_method("outlangsplat"), encoder_from_spec(), tmp_path / "offline")
    offline = LanguageMap.load(tmp_path / "offline" / "language_map.npz")
    assert streamed.encoder == offline.encoder
    assert np.array_equal(streamed.observed, offline.observed) and streamed.observed.sum() > 1000
    np.testing.assert_array_equal(streamed.features, offline.features)


@pytest.mark.timeout(600)
@pytest.mark.parametrize(
    ("victim", "kills"), [("ingest", 1), ("region_encoder", 1), ("refiner", 1), ("query_server", 1), ("accumulator", 2)]
)
def test_any_node_killed_mid_flight_loses_nothing(victim, kills, tiny, tmp_path, offline_map):
    """kill -9 of each of the other four nodes (the accumulator once: the test above; here twice
    in a row, the second time as soon as it is back) once two views are stored: the supervisor
    restarts it, every frame is in the store once, and the final map is that of an
    uninterrupted run (to float16 rounding: after a kill, views may be stored in another
    order, which changes the order of each Gaussian's sums)."""
    import numpy as np

    from olsplat_nodes.storage import LanguageMap

    scene, summary = tiny
    run_dir = tmp_path / "run"
    assert fly_and_kill(scene, run_dir, victim, kills=kills) == 0
    names = ObservationStore(run_dir / "store", 1).names()
    assert sorted(names) == sorted(set(names)) and len(names) == summary["views"]  # every frame, once
    record = latest_map(run_dir / "map")
    assert record["final"] and record["views"] == summary["views"]
    streamed = LanguageMap.load(record["path"])
    np.testing.assert_array_equal(streamed.observed, offline_map.observed)
    np.testing.assert_allclose(streamed.features, offline_map.features, atol=2e-3, rtol=0)
