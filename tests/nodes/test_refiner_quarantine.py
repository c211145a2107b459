"""A store segment damaged on disk, seen by the running refiner: skipped, ERROR in its heartbeat
naming the segment, and the map is still made from the other views."""

from __future__ import annotations

import shutil

import pytest
import zmq

from olsplat_msgs import DiagnosticStatus, EndOfStream, MapUpdated
from olsplat_nodes.storage import LanguageMap, latest_map
from tests.helpers import every, wait_for

from .conftest import Heartbeats, NodeThread, Tap, raw_socket, refiner, send_msg

pytestmark = pytest.mark.timeout(120)


def test_the_refiner_reports_a_damaged_segment_and_still_makes_the_map(ctx, sockdir, tmp_path, tiny, tiny_run):
    scene, _ = tiny
    store = tmp_path / "store"
    shutil.copytree(tiny_run / "store", store)  # one good view (000000)
    damaged = store / "views" / "000001"
    shutil.copytree(store / "views" / "000000", damaged)  # a second segment, then damaged on disk
    (damaged / "name.txt").write_text("frame_9999.jpg")
    (damaged / "weights.npy").write_bytes(b"\x93NUMPY truncated")
    observations = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/observations.sock", bind=True)
    beats = Heartbeats(ctx)
    maps = Tap(ctx, f"ipc://{sockdir}/map.sock", ["map"])
    node = refiner(scene, sockdir, store, tmp_path / "map", beats.endpoint)
    try:
        with NodeThread(node) as running:
            beats.wait("refiner", lambda v: True, 20, "a first heartbeat (in sync)")
            wait_for(
                lambda: any(m.final for m in maps.got(MapUpdated)),
                60,
                "the final MapUpdated",
                step=every(
                    0.3,
                    lambda: send_msg(
                        observations,
                        EndOfStream(seq=1, frame_id="camera", source="test", frames=2),
                        "observations",
                    ),
                ),
            )
            assert running.join(10) == 0
        beats.wait("refiner", lambda v: v.get("quarantined") == 1, 10, "quarantined == 1")
        last = [m for m in beats.of_type(DiagnosticStatus) if m.node == "refiner"][-1]
        assert last.level == 2 and "000001" in last.message and "damaged" in last.message, last.message
        assert last.values["quarantined"] == 1
        assert (damaged / "QUARANTINED.txt").exists()
        record = latest_map(tmp_path / "map")
        assert record["final"] and LanguageMap.load(record["path"]).observed.any()
        assert not maps.undecodable
    finally:
        for sock in (observations, beats, maps):
            sock.close()
