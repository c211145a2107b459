"""An accumulator whose disk will not take a view: the node stays up, does not acknowledge the
view, reports the error (which names the file, the reason and the free space) as its status,
leaves no half-written file, and stores the view once there is room (the re-sent view, as a
lossless ingest sends it).

The node runs in its own process (``python -m olsplat_nodes.nodes accumulator``) on real
sockets; the "full disk" is the operating system's file-size limit (RLIMIT_FSIZE), set on the
running node by ``prlimit`` once it is ready, so that every write of a view fails (EFBIG, with
SIGXFSZ ignored as a node's parent may leave it) and lifted again to make room.
"""

from __future__ import annotations

import json
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import zmq

from olsplat_msgs import DiagnosticStatus, EndOfStream, ObservationsAdded, encode
from tests.helpers import every, wait_for

from .conftest import Heartbeats, Tap, raw_socket, send, send_msg

pytestmark = pytest.mark.timeout(240)

ROOT = Path(__file__).resolve().parents[2]


def _ignore_sigxfsz() -> None:  # in the child before exec: an ignored signal stays ignored
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)


def _statuses(beats: Heartbeats) -> list[DiagnosticStatus]:
    beats.poll(50)
    return [m for m in beats.of_type(DiagnosticStatus) if m.node == "accumulator"]


def test_a_view_the_disk_will_not_take_is_reported_not_acknowledged_and_stored_once_there_is_room(
    ctx, sockdir, tmp_path, tiny, region_features
):
    from olsplat_nodes.aggregate import ObservationStore
    from olsplat_nodes.scene import read_ply

    scene, _ = tiny
    regions = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/regions.sock", bind=True)
    beats = Heartbeats(ctx)
    observations = Tap(ctx, f"ipc://{sockdir}/observations.sock", ["observations"])
    params = {
        "map": str(scene / "map" / "point_cloud.ply"),
        "store": str(tmp_path / "store"),
        "views": str(tmp_path / "views"),
        "regions_in": f"ipc://{sockdir}/regions.sock",
        "observations_out": f"ipc://{sockdir}/observations.sock",
        "diagnostics": beats.endpoint,
    }
    node = subprocess.Popen(
        [sys.executable, "-m", "olsplat_nodes.nodes", "accumulator", "--params-json", json.dumps(params)],
        cwd=ROOT,
        stdout=subprocess.PIPE,  # a pipe, not a file: the file-size limit would cut a log file too
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=_ignore_sigxfsz,
    )
    good = encode(region_features, "regions")
    try:
        wait_for(  # ready and subscribed: an EndOfStream comes back on the observations topic
            lambda: observations.got(EndOfStream),
            120,
            "the accumulator to forward EndOfStream",
            step=every(0.2, lambda: send_msg(regions, EndOfStream(frame_id="sync", source="test"), "regions")),
        )
        _, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.prlimit(node.pid, resource.RLIMIT_FSIZE, (1024, hard))  # no file past 1 KB: a full disk

        send(regions, good)
        failed = wait_for(
            lambda: [s for s in _statuses(beats) if s.level == DiagnosticStatus.ERROR],
            30,
            "an ERROR status from the accumulator",
        )[-1]
        assert region_features.name in failed.message and "could not be written" in failed.message, failed
        assert "MB free on its disk" in failed.message and str(tmp_path) in failed.message, failed
        assert failed.values["store_errors"] >= 1
        assert node.poll() is None, "the accumulator died of a full disk"
        assert not observations.got(ObservationsAdded), "a view that is not on the disk was acknowledged"
        left = sorted(p.name for p in tmp_path.rglob("*") if p.name.endswith(".tmp"))
        assert not left, f"half-written files left: {left}"

        resource.prlimit(node.pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, hard))  # room again
        acks = wait_for(
            lambda: observations.got(ObservationsAdded),
            60,
            "the view acknowledged once there is room",
            step=every(1.0, lambda: send(regions, good)),  # the ingest's re-sends
        )
        assert acks[0].name == region_features.name and not acks[0].duplicate and acks[0].views_in_store == 1
        wait_for(
            lambda: [s for s in _statuses(beats) if s.level == DiagnosticStatus.OK and s.values.get("views") == 1],
            30,
            "the status back to OK with the view stored",
        )
        assert node.poll() is None
    finally:
        node.send_signal(signal.SIGTERM)
        try:
            output, _ = node.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            node.kill()
            output, _ = node.communicate()
        regions.close()
        beats.close()
        observations.close()
    assert "not stored" in output and "not acknowledged" in output, output[-3000:]
    store = ObservationStore(tmp_path / "store", len(read_ply(scene / "map" / "point_cloud.ply")))
    assert store.names() == [region_features.name]


def test_a_map_the_disk_will_not_take_is_reported_and_written_by_a_later_pass(ctx, sockdir, tmp_path, tiny, tiny_run):
    """The refiner's final pass cannot write its snapshot: the node stays up and reports the
    error (naming the snapshot's file), ``latest.json`` is not written, no temporary file stays;
    once there is room its next pass writes the final map, announces it and the node ends."""
    import shutil

    from olsplat_msgs import MapUpdated

    scene, _ = tiny
    store, map_dir = tmp_path / "store", tmp_path / "map"
    shutil.copytree(tiny_run / "store", store, ignore=shutil.ignore_patterns("views"))  # the manifest, no view yet
    beats = Heartbeats(ctx)
    observations = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/observations.sock", bind=True)
    maps = Tap(ctx, f"ipc://{sockdir}/map.sock", ["map"])
    params = {
        "map": str(scene / "map" / "point_cloud.ply"),
        "store": str(store),
        "map_dir": str(map_dir),
        "period_s": 1.0,
        "observations_in": f"ipc://{sockdir}/observations.sock",
        "map_out": f"ipc://{sockdir}/map.sock",
        "diagnostics": beats.endpoint,
    }
    node = subprocess.Popen(
        [sys.executable, "-m", "olsplat_nodes.nodes", "refiner", "--params-json", json.dumps(params)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=_ignore_sigxfsz,
    )
    try:
        wait_for(
            lambda: [m for m in beats.got(DiagnosticStatus) if m.node == "refiner"], 120, "the refiner's heartbeat"
        )
        _, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.prlimit(node.pid, resource.RLIMIT_FSIZE, (1024, hard))  # no file past 1 KB: a full disk
        shutil.copytree(tiny_run / "store" / "views", store / "views")  # the flight's one view arrives ...
        wait_for(  # ... and the flight ends
            lambda: [
                m for m in beats.got(DiagnosticStatus) if m.node == "refiner" and m.level == DiagnosticStatus.ERROR
            ],
            60,
            "an ERROR status from the refiner",
            step=every(0.5, lambda: send_msg(observations, EndOfStream(frame_id="end", source="test"), "observations")),
        )
        failed = [m for m in beats.of_type(DiagnosticStatus) if m.node == "refiner" and m.level == 2][-1]
        assert "not written" in failed.message and "language_map_000001.npz" in failed.message, failed
        assert failed.values["snapshot_errors"] >= 1
        assert node.poll() is None, "the refiner died of a full disk"
        assert not (map_dir / "latest.json").exists()
        assert not [p.name for p in map_dir.iterdir() if p.name.endswith(".tmp")]
        assert not [m for m in maps.got(MapUpdated) if m.final]

        resource.prlimit(node.pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, hard))  # room again
        final = wait_for(
            lambda: [m for m in maps.got(MapUpdated) if m.final] or (node.poll() is not None and ["exited"]),
            60,
            "the final map once there is room",
        )
        assert final[0] != "exited", node.communicate()[0][-3000:]
        assert final[0].views == 1 and final[0].version == 1
        assert node.wait(timeout=30) == 0  # it ends after its final map, as after any flight
    finally:
        if node.poll() is None:
            node.kill()
        output, _ = node.communicate()
        beats.close()
        observations.close()
        maps.close()
    assert "not written" in output, output[-3000:]
    assert json.loads((map_dir / "latest.json").read_text())["final"] is True
