"""A lossless replay does not wait the full acknowledgement timeout for the frames it sent
before the graph was listening: until the first acknowledgement it sends them again after
``ack_timeout_start_s``, doubling; once the graph has answered, ``ack_timeout_s`` applies.

The ingest runs as its own process, as the launcher runs it (a node in a test thread that is
stopped while frames are in flight has tripped a libzmq assertion on disconnect, taking the
whole test process with it)."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest
import zmq

from olsplat_msgs import ImageFrame, ObservationsAdded
from tests.helpers import wait_for

from .conftest import Tap, raw_socket, send_msg

pytestmark = pytest.mark.timeout(120)


def test_frames_are_resent_quickly_until_the_graph_answers(ctx, sockdir, tmp_path, tiny):
    scene, _ = tiny
    acks = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/acks.sock", bind=True)
    params = {
        "source": str(scene / "replay.mcap"),
        "fast": True,
        "window": 2,
        "ack_timeout_s": 60.0,
        "ack_timeout_start_s": 0.3,
        "frames_out": f"ipc://{sockdir}/frames.sock",
        "acks_in": f"ipc://{sockdir}/acks.sock",
        "map_in": f"ipc://{sockdir}/map.sock",
        "state_file": str(tmp_path / "acknowledged.txt"),
    }
    log = open(tmp_path / "ingest.log", "wb")  # closed in finally
    node = subprocess.Popen(
        [sys.executable, "-m", "olsplat_nodes.nodes", "ingest", "--params-json", json.dumps(params)],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    frames = Tap(ctx, f"ipc://{sockdir}/frames.sock", ["frames"])

    def copies(name: str) -> int:
        return sum(frame.name == name for frame in frames.got(ImageFrame, 0))

    try:
        start = time.monotonic()
        # sends at about 0, 0.3, 0.9, 2.1 s: three copies long before the 60 s timeout
        wait_for(lambda: copies("frame_0001.jpg") >= 3, 30, "three copies of frame_0001 without an acknowledgement")
        assert time.monotonic() - start < 40
        ack = ObservationsAdded(seq=1, frame_id="camera", name="frame_0000.jpg")
        wait_for(
            lambda: copies("frame_0002.jpg") >= 1,
            10,
            "frame_0002 once frame_0000 is acknowledged",
            step=lambda: send_msg(acks, ack, "observations"),
        )
        # the graph has answered: frame_0001, still unacknowledged, now waits the full 60 s
        seen = copies("frame_0001.jpg")
        deadline = time.monotonic() + 4.0
        while time.monotonic() < deadline:
            frames.poll(100)
        assert copies("frame_0001.jpg") == seen
        assert node.poll() is None, (tmp_path / "ingest.log").read_text()
    finally:
        frames.close()
        acks.close()
        node.terminate()
        node.wait(30)
        log.close()


def test_a_frame_left_unacknowledged_turns_the_ingest_warn_and_a_finished_one_is_not_stale(
    ctx, sockdir, tmp_path, tiny
):
    """Once the graph has answered, a frame waiting longer than ``ack_timeout_s`` for its
    acknowledgement is a WARN naming it (the stage after the ingest is stuck), not OK. After the
    final map its last heartbeat says it finished (which a collector never calls STALE)."""
    from olsplat_msgs import DiagnosticStatus, MapUpdated

    from .conftest import Heartbeats

    scene, _ = tiny
    acks = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/acks.sock", bind=True)
    beats = Heartbeats(ctx)
    params = {
        "source": str(scene / "replay.mcap"),
        "fast": True,
        "window": 2,
        "ack_timeout_s": 2.0,
        "ack_timeout_start_s": 0.3,
        "frames_out": f"ipc://{sockdir}/frames.sock",
        "acks_in": f"ipc://{sockdir}/acks.sock",
        "map_in": f"ipc://{sockdir}/map.sock",
        "state_file": str(tmp_path / "acknowledged.txt"),
        "diagnostics": beats.endpoint,
    }
    log = open(tmp_path / "ingest.log", "wb")  # closed in finally
    node = subprocess.Popen(
        [sys.executable, "-m", "olsplat_nodes.nodes", "ingest", "--params-json", json.dumps(params)],
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    frames = Tap(ctx, f"ipc://{sockdir}/frames.sock", ["frames"])

    def ack(name: str):
        return lambda: send_msg(acks, ObservationsAdded(seq=1, frame_id="camera", name=name), "observations")

    def status() -> DiagnosticStatus | None:
        beats.poll(50)
        mine = [m for m in beats.of_type(DiagnosticStatus) if m.node == "ingest"]
        return mine[-1] if mine else None

    try:
        wait_for(lambda: frames.got(ImageFrame, 0), 30, "the first frame", step=lambda: frames.poll(50))
        wait_for(
            lambda: (s := status()) and s.values.get("acknowledged") == 1,
            20,
            "frame_0000 taken",
            step=ack("frame_0000.jpg"),
        )
        stuck = wait_for(
            lambda: (s := status()) and s.level == DiagnosticStatus.WARN and s, 20, "a WARN for frame_0001"
        )
        assert "frame frame_0001.jpg unacknowledged for" in stuck.message, stuck.message
        assert stuck.values["oldest_unacknowledged_s"] >= 2.0  # rounded to 0.1 s
        for i in range(1, 12):  # acknowledge the rest: the WARN ends
            wait_for(lambda i=i: (s := status()) and s.values.get("acknowledged") == i + 1, 20, f"frame {i}",
                     step=ack(f"frame_{i:04d}.jpg"))  # fmt: skip
        final = MapUpdated(seq=1, frame_id="map", final=True)
        wait_for(lambda: node.poll() is not None, 30, "the ingest ending after the final map",
                 step=lambda: send_msg(acks, final, "map"))  # fmt: skip
        last = status()
        assert node.returncode == 0 and last.level == DiagnosticStatus.OK and last.values.get("finished") == 1, last
        assert last.message.startswith("finished: 12 frames acknowledged"), last.message
    finally:
        frames.close()
        acks.close()
        beats.close()
        if node.poll() is None:
            node.terminate()
        node.wait(30)
        log.close()
