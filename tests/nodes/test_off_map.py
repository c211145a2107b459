"""Views that do not see the prior map, through the real graph: the 24 real Caliterra photos
(geotagged, ``exif_folder``) over the tiny simulated town's map (another place) are refused one
by one with a WARN, and the accumulator's status turns ERROR ("views do not overlap the map")
after the first five; the query server's status reply shows it to the ground station. The run
records its prior map on the way."""

from __future__ import annotations

import hashlib

import pytest
import zmq

from olsplat_msgs import DiagnosticStatus, StatusRequest
from olsplat_nodes.launcher import Supervisor
from olsplat_nodes.storage import ObservationStore
from olsplat_nodes.storage.prior import read_prior_record, recorded_prior_map
from olsplat_nodes.transport import NoReply, QueryClient
from tests.helpers import free_port, wait_for

from .conftest import Background, launch_tiny


def _accumulator_status(client: QueryClient) -> dict | None:
    try:
        reply = client.request(StatusRequest(request_id="s"))
    except NoReply:
        return None
    return next((n for n in reply.nodes if n["node"] == "accumulator"), None)


@pytest.mark.timeout(600)
def test_real_photos_over_another_places_map_turn_the_accumulator_error(tiny, shared_data, tmp_path):
    scene, _ = tiny
    port = free_port()
    run_dir = tmp_path / "run"
    photos = shared_data / "caliterra"
    config = launch_tiny(scene, run_dir, port, "ingest.source_kind=exif_folder", f"ingest.source={photos}")
    supervisor = Supervisor(config)
    running = Background(supervisor)
    client = QueryClient(zmq.Context.instance(), f"tcp://127.0.0.1:{port}", timeout_s=10.0)
    try:
        status = wait_for(
            lambda: (s := _accumulator_status(client)) and s["level"] == DiagnosticStatus.ERROR and s,
            480,
            "the accumulator's status to turn ERROR",
        )
    finally:
        client.close()
        supervisor.request_stop()
        running.thread.join(60)
    message = status["message"]
    assert message.startswith("views do not overlap the map: wrong map, wrong georeference or wrong camera model?")
    assert "The first 5 views were refused" in message and "IMG_9354.jpg: map coverage" in message, message
    assert status["values"]["views_refused"] >= 5
    log = (run_dir / "logs" / "accumulator.log").read_text()
    refused = [line for line in log.splitlines() if "WARNING" in line and "refused" in line]
    assert len(refused) >= 5 and "IMG_9354.jpg" in refused[0] and "not aggregated" in refused[0], refused
    # refused views are acknowledged (the ingest moved on past the first five) but not in the store
    stored = ObservationStore(run_dir / "store", 1).names() if (run_dir / "store").is_dir() else []
    assert not {f"IMG_93{n}.jpg" for n in range(54, 59)} & set(stored), stored
    # the run recorded its prior map (path and SHA-256), hashed off the node's loop
    ply = (scene / "map" / "point_cloud.ply").resolve()
    assert recorded_prior_map(run_dir / "store") == ply
    assert read_prior_record(run_dir / "store").sha256 == hashlib.sha256(ply.read_bytes()).hexdigest()
    assert "SHA-256" in log and "hashed in" in log
