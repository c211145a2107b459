"""Field setup: the ingest node on its live and photo sources, and launch/field_drone.yaml with no
camera attached (composed: every node a thread of the launcher, the ground link over TCP + CURVE)."""

from __future__ import annotations

import io
import threading
from pathlib import Path

import pytest
import zmq

from olsplat_msgs import DiagnosticStatus, ImageFrame, StatusRequest
from olsplat_nodes.launcher import Supervisor, load_launch
from olsplat_nodes.nodes.ingest import IngestNode
from olsplat_nodes.scene.geodesy import read_georef
from olsplat_nodes.sources import discover_devices
from olsplat_nodes.transport import QueryClient, curve
from tests.helpers import free_port, wait_for

from ..sources.conftest import TRACK, write_photo
from .conftest import Heartbeats, NodeThread, Tap

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def no_device():
    if discover_devices():
        pytest.skip("a DepthAI device is attached: the no-device tests do not apply")


def test_ingest_without_camera_heartbeats_the_error_and_keeps_running(ctx, sockdir, no_device):
    beats = Heartbeats(ctx)
    node = IngestNode(
        "ingest",
        {
            "source_kind": "depthai",
            "depthai_retry_s": 0.2,
            "lossless": False,
            "diagnostics": beats.endpoint,
            "frames_out": f"ipc://{sockdir}/f.sock",
            "acks_in": f"ipc://{sockdir}/a.sock",
            "map_in": f"ipc://{sockdir}/m.sock",
            "state_file": "",
        },
        ctx,
    )
    try:
        with NodeThread(node) as thread:

            def errors():
                beats.poll(50)
                return [
                    m
                    for m in beats.of_type(DiagnosticStatus)
                    if m.node == "ingest" and m.level == DiagnosticStatus.ERROR
                ]

            wait_for(lambda: len(errors()) >= 3, 20, "three ERROR heartbeats")
            status = errors()[-1]
            assert (
                status.message.startswith("no DepthAI device found") and status.values["source_discovery_attempts"] >= 1
            )
            thread.assert_running()
        assert thread.code == 130
    finally:
        beats.close()


def test_ingest_streams_geotagged_photos(ctx, sockdir, tmp_path):
    for i, (lat, lon, alt) in enumerate(TRACK):
        write_photo(tmp_path / f"IMG_{i}.jpg", lat, lon, alt, f"2024:05:01 10:00:{i:02d}", seed=i)
    tap = Tap(ctx, f"ipc://{sockdir}/f.sock", ["frames"])
    node = IngestNode(
        "ingest",
        {
            "source_kind": "exif_folder",
            "source": str(tmp_path),
            "rate_hz": 2.0,
            "lossless": False,
            "frames_out": f"ipc://{sockdir}/f.sock",
            "acks_in": f"ipc://{sockdir}/a.sock",
            "map_in": f"ipc://{sockdir}/m.sock",
            "state_file": "",
            "georef_out": str(tmp_path / "run" / "map" / "georef.json"),
        },
        ctx,
    )
    try:
        with NodeThread(node):
            frames = wait_for(
                lambda: tap.got(ImageFrame), 20, "photos on the frame topic"
            )  # (a slow joiner may miss the first)
        frame = frames[0]
        assert (
            frame.name.startswith("IMG_")
            and frame.image.shape == (120, 160, 3)
            and frame.world_from_camera[2, 2] == pytest.approx(-1)
        )
    finally:
        tap.close()
    # the run's answers are georeferenced by the photos' ENU origin: the first photo's GPS, MSL
    georef = read_georef(tmp_path / "run" / "map" / "georef.json")
    assert (georef.latitude, georef.longitude, georef.altitude) == pytest.approx(TRACK[0], abs=1e-9)
    assert georef.axes == "enu" and georef.height_ref == "msl" and "first photo" in georef.source


@pytest.mark.slow
def test_field_drone_launch_without_camera(tiny, tmp_path, no_device):
    scene, _ = tiny
    keys = tmp_path / "keys"
    curve.generate(keys, "drone")
    curve.generate(keys / "allowed", "ground")
    port = free_port()
    ply = scene / "map" / "point_cloud.ply"
    overrides = [
        "launch.compose=true",
        "launch.stop_timeout_s=20",
        f"query_server.query_endpoint=tcp://127.0.0.1:{port}",
        f"query_server.server_secret={keys / 'drone.key_secret'}",
        f"query_server.allow_dir={keys / 'allowed'}",
        f"query_server.map={ply}",
        f"accumulator.map={ply}",
        f"refiner.map={ply}",
        "ingest.depthai_retry_s=0.5",
        f"ingest.telemetry_url={tmp_path / 'no_autopilot_tty'}",
    ]
    config = load_launch(REPO / "launch" / "field_drone.yaml", overrides=overrides, run_dir=str(tmp_path / "run"))
    supervisor = Supervisor(config, stdout=io.StringIO())
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(supervisor.run()), daemon=True)
    thread.start()
    client = QueryClient(
        zmq.Context.instance(),
        f"tcp://127.0.0.1:{port}",
        timeout_s=5.0,
        keys=curve.ClientKeys(keys / "allowed" / "ground.key_secret", keys / "drone.key"),
    )
    try:

        def graph():
            try:
                reply = client.request(StatusRequest(request_id="field"))
            except Exception:
                return None
            nodes = {n["node"]: n for n in reply.nodes}
            if (
                set(nodes) >= {"query_server", "ingest", "region_encoder", "accumulator", "refiner"}
                and nodes["ingest"]["level"] == 2
            ):
                return nodes
            return None

        nodes = wait_for(graph, 120, "every node's status with the ingest at ERROR", interval_s=0.5)
        ingest = nodes["ingest"]
        assert ingest["message"].startswith("no DepthAI device found") and "telemetry port" in ingest["message"]
        assert ingest["values"]["source_telemetry_connected"] == 0
        for name in ("query_server", "region_encoder", "accumulator", "refiner"):
            assert nodes[name]["level"] == 0, nodes[name]
        # the heartbeat keeps coming: a later status is still fresh, not STALE
        again = wait_for(graph, 20, "a later status", interval_s=0.5)
        assert again["ingest"]["age_s"] < 3 and again["ingest"]["level"] == 2
        assert thread.is_alive()
    finally:
        client.close()
        supervisor.request_stop()
        thread.join(60)
    assert not thread.is_alive() and result and result[0] in (0, 130, 143)
