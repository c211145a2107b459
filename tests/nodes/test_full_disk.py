"""Nodes on a full disk: none dies of it, none leaves a half-written file, each reports the
error (naming the file, the reason and the free space) as its status and goes on once there is
room. The accumulator does not acknowledge a view it could not store and stores it when it is
sent again (as a lossless ingest does); the refiner keeps its last map and writes the final one
by a later pass; the ingest goes on with the flight when it cannot record an acknowledgement.

Each node runs in its own process (``python -m olsplat_nodes.nodes NODE``) on real sockets; the
"full disk" is the operating system's file-size limit (RLIMIT_FSIZE), set on the running node by
``prlimit`` once it is ready, so that its writes fail (EFBIG, or a short write, with SIGXFSZ
ignored as a node's parent may leave it), and lifted again to make room.
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

from .conftest import Heartbeats, Tap, accumulator_params, raw_socket, send, send_msg

pytestmark = pytest.mark.timeout(240)

ROOT = Path(__file__).resolve().parents[2]


def _ignore_sigxfsz() -> None:  # in the child before exec: an ignored signal stays ignored
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)


def _start(node: str, params: dict) -> subprocess.Popen:
    """The node in its own process, its log in a pipe (a file would be cut by the limit too)."""
    return subprocess.Popen(
        [sys.executable, "-m", "olsplat_nodes.nodes", node, "--params-json", json.dumps(params)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=_ignore_sigxfsz,
    )


def _stop(node: subprocess.Popen) -> str:
    """Ask the node to stop (SIGTERM; killed after 30 s) and return its log."""
    if node.poll() is None:
        node.terminate()
    try:
        return node.communicate(timeout=30)[0]
    except subprocess.TimeoutExpired:
        node.kill()
        return node.communicate()[0]


def _full_disk(pid: int, room_bytes: int | None) -> None:
    """No file of process ``pid`` may grow past ``room_bytes`` (None: no limit), as on a full disk."""
    _, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.prlimit(pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY if room_bytes is None else room_bytes, hard))


def _statuses(beats: Heartbeats) -> list[DiagnosticStatus]:
    beats.poll(50)
    return [m for m in beats.of_type(DiagnosticStatus) if m.node == "accumulator"]


@pytest.mark.parametrize("features", ["2d", "2d3d"])
def test_a_view_the_disk_will_not_take_is_reported_not_acknowledged_and_stored_once_there_is_room(
    ctx, sockdir, tmp_path, tiny, region_features, features
):
    """With 2D features the view's photo is refused (1 KB of room); with the 3D branch the
    photo fits and the store's segment is refused, after h has trained on the view: the branch
    is put back as the disk has it, so the view stored later has trained h once."""
    import cv2
    import numpy as np

    from olsplat_nodes.scene import read_ply
    from olsplat_nodes.storage import ObservationStore

    scene, _ = tiny
    room = 1024
    if features == "2d3d":  # the photo as save_view encodes it, and its camera record, fit
        photo = cv2.imencode(
            ".jpg", np.ascontiguousarray(np.array(region_features.image)[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95]
        )[1]
        room = len(photo) + 4096
    regions = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/regions.sock", bind=True)
    beats = Heartbeats(ctx)
    observations = Tap(ctx, f"ipc://{sockdir}/observations.sock", ["observations"])
    params = accumulator_params(scene, tmp_path, sockdir, beats, features=features)
    node = _start("accumulator", params)
    good = encode(region_features, "regions")
    try:
        wait_for(  # ready and subscribed: an EndOfStream comes back on the observations topic
            lambda: observations.got(EndOfStream),
            120,
            "the accumulator to forward EndOfStream",
            step=every(0.2, lambda: send_msg(regions, EndOfStream(frame_id="sync", source="test"), "regions")),
        )
        _full_disk(node.pid, room)

        send(regions, good)
        failed = wait_for(
            lambda: [s for s in _statuses(beats) if s.level == DiagnosticStatus.ERROR],
            30,
            "an ERROR status from the accumulator",
        )[-1]
        assert region_features.name in failed.message and "could not be written" in failed.message, failed
        assert "MB free on its disk" in failed.message and str(tmp_path) in failed.message, failed
        assert failed.values["store_errors"] >= 1
        if features == "2d3d":  # refused at the segment, with the photo on the disk
            assert failed.message.endswith(f"'{tmp_path / 'store'}'"), failed
        assert node.poll() is None, "the accumulator died of a full disk"
        assert not observations.got(ObservationsAdded), "a view that is not on the disk was acknowledged"
        left = sorted(p.name for p in tmp_path.rglob("*") if p.name.endswith(".tmp"))
        assert not left, f"half-written files left: {left}"

        _full_disk(node.pid, None)  # room again
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
        output = _stop(node)
        regions.close()
        beats.close()
        observations.close()
    assert "not stored" in output and "not acknowledged" in output, output[-3000:]
    store = ObservationStore(tmp_path / "store", len(read_ply(scene / "map" / "point_cloud.ply")))
    assert store.names() == [region_features.name]
    if features == "2d3d":  # h trained on the view once: the failed attempt's training was undone
        with np.load(tmp_path / "store" / "branch.npz") as branch:
            assert len(branch["losses"]) == 1, branch["losses"]


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
    node = _start("refiner", params)
    try:
        wait_for(
            lambda: [m for m in beats.got(DiagnosticStatus) if m.node == "refiner"], 120, "the refiner's heartbeat"
        )
        _full_disk(node.pid, 1024)
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

        _full_disk(node.pid, None)  # room again
        final = wait_for(
            lambda: [m for m in maps.got(MapUpdated) if m.final] or (node.poll() is not None and ["ended"]),
            60,
            "the final map once there is room",
        )
        assert final[0] != "ended", f"the refiner ended without announcing a final map:\n{_stop(node)[-3000:]}"
        assert final[0].views == 1 and final[0].version == 1
        assert node.wait(timeout=30) == 0  # it ends after its final map, as after any flight
    finally:
        output = _stop(node)
        beats.close()
        observations.close()
        maps.close()
    assert "not written" in output, output[-3000:]
    assert json.loads((map_dir / "latest.json").read_text())["final"] is True


def test_an_acknowledgement_the_disk_will_not_record_does_not_stop_the_flight(ctx, sockdir, tmp_path, tiny):
    """The ingest cannot append an acknowledged frame to its state file: it goes on with the
    flight (the next frame goes out), reports the error as its status (WARN, naming the file),
    and leaves no half line: once there is room the next name is on a line of its own."""
    from olsplat_msgs import ImageFrame, ObservationsAdded

    scene, _ = tiny
    beats = Heartbeats(ctx)
    acks = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/acks.sock", bind=True)
    frames = Tap(ctx, f"ipc://{sockdir}/frames.sock", ["frames"])
    state = tmp_path / "acknowledged.txt"
    state.write_text("frame_9999.jpg\n")  # a line from an earlier run: the limit sits just past it
    params = {
        "source": str(scene / "replay.mcap"),
        "fast": True,
        "window": 1,
        "ack_timeout_s": 60.0,
        "ack_timeout_start_s": 0.3,
        "frames_out": f"ipc://{sockdir}/frames.sock",
        "acks_in": f"ipc://{sockdir}/acks.sock",
        "map_in": f"ipc://{sockdir}/map.sock",
        "state_file": str(state),
        "diagnostics": beats.endpoint,
    }
    node = _start("ingest", params)

    def sent(name: str) -> bool:
        return any(frame.name == name for frame in frames.got(ImageFrame, 0))

    def acknowledge(name: str) -> None:
        send_msg(acks, ObservationsAdded(seq=1, frame_id="camera", name=name), "observations")

    try:
        wait_for(lambda: sent("frame_0000.jpg"), 60, "the first frame")
        _full_disk(node.pid, state.stat().st_size + 5)  # room for 5 bytes: part of a line
        wait_for(
            lambda: sent("frame_0001.jpg"), 20, "the next frame", step=every(0.3, lambda: acknowledge("frame_0000.jpg"))
        )
        warned = wait_for(
            lambda: [m for m in beats.got(DiagnosticStatus) if m.node == "ingest" and m.level == DiagnosticStatus.WARN],
            20,
            "a WARN status from the ingest",
        )[-1]
        assert "frame_0000.jpg" in warned.message and str(state) in warned.message, warned
        assert warned.values["state_errors"] >= 1
        assert state.read_text() == "frame_9999.jpg\n"  # as it was: no half line

        _full_disk(node.pid, None)  # room again
        wait_for(
            lambda: sent("frame_0002.jpg"),
            20,
            "the frame after",
            step=every(0.3, lambda: acknowledge("frame_0001.jpg")),
        )
        wait_for(lambda: state.read_text().endswith("frame_0001.jpg\n"), 10, "the next name recorded")
        assert state.read_text().splitlines() == ["frame_9999.jpg", "frame_0001.jpg"]
        assert node.poll() is None
    finally:
        output = _stop(node)
        beats.close()
        acks.close()
        frames.close()
    assert "not recorded as acknowledged" in output, output[-3000:]


@pytest.mark.parametrize("warn_views", [0, 10**15])
def test_the_accumulator_tells_how_many_more_views_its_disk_holds(
    ctx, sockdir, tmp_path, tiny, region_features, warn_views
):
    """After a stored view the status carries the free space, the run's bytes per view (photo,
    camera and store segment, as on the disk) and the views the disk holds at that rate; below
    ``disk_warn_views`` (here: more than any disk holds) the status is a WARN that says so."""
    import shutil

    import numpy as np

    from olsplat_nodes.nodes.accumulator import AccumulatorNode

    from .conftest import NodeThread

    scene, _ = tiny
    regions = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/regions.sock", bind=True)
    beats = Heartbeats(ctx)
    observations = Tap(ctx, f"ipc://{sockdir}/observations.sock", ["observations"])
    params = accumulator_params(scene, tmp_path, sockdir, beats, disk_warn_views=warn_views)
    try:
        with NodeThread(AccumulatorNode("accumulator", params)) as running:
            wait_for(
                lambda: observations.got(ObservationsAdded),
                60,
                "the view acknowledged",
                step=every(1.0, lambda: send(regions, encode(region_features, "regions"))),
            )
            status = wait_for(
                lambda: [s for s in _statuses(beats) if "disk_views_left" in s.values], 30, "a status with disk figures"
            )[-1]
            running.assert_running()
    finally:
        regions.close()
        beats.close()
        observations.close()
    values = status.values
    segment = tmp_path / "store" / "views" / "000000"
    arrays = sum(np.load(f, mmap_mode="r").nbytes for f in segment.glob("*.npy"))
    written = arrays + sum(f.stat().st_size for f in (tmp_path / "views").iterdir())
    assert values["disk_mb_per_view"] == pytest.approx(written / 2**20, abs=0.001), (values, written)
    free_mb = shutil.disk_usage(tmp_path).free / 2**20
    assert values["disk_free_mb"] == pytest.approx(free_mb, rel=0.05), values
    expected_left = values["disk_free_mb"] / (values["disk_mb_per_view"] * 1.2)
    assert values["disk_views_left"] == pytest.approx(expected_left, rel=0.01), values
    if warn_views:
        assert status.level == DiagnosticStatus.WARN, status
        assert status.message.startswith(f"disk nearly full: room for ~{values['disk_views_left']} more views at")
        assert str(tmp_path / "store") in status.message
    else:
        assert status.level == DiagnosticStatus.OK and status.message == "1 views in the store", status


def test_the_disk_warning_ends_once_space_is_made_without_new_views(ctx, sockdir, tmp_path, tiny, region_features):
    """The accumulator reads the free space again every few seconds, not only after a view: an
    operator who frees space mid-flight (or while the drone waits) sees the WARN go. Space is
    taken and given back by a preallocated file on the store's disk, the warning threshold set
    halfway between the views the disk holds with and without it."""
    import os
    import shutil

    from olsplat_nodes.nodes.accumulator import DISK_RECHECK_S, AccumulatorNode

    from .conftest import NodeThread

    scene, _ = tiny
    hog_gb = 4

    def run_until(folder: Path, warn_views: int, until, what: str, between=None):
        regions = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/regions.sock", bind=True)
        beats = Heartbeats(ctx)
        observations = Tap(ctx, f"ipc://{sockdir}/observations.sock", ["observations"])
        params = accumulator_params(scene, folder, sockdir, beats, disk_warn_views=warn_views)
        try:
            with NodeThread(AccumulatorNode("accumulator", params)) as running:
                wait_for(
                    lambda: observations.got(ObservationsAdded),
                    60,
                    "the view acknowledged",
                    step=every(1.0, lambda: send(regions, encode(region_features, "regions"))),
                )
                first = wait_for(lambda: [s for s in _statuses(beats) if "disk_views_left" in s.values], 30, what)
                last = first[-1]
                if between is not None:
                    between()
                    last = wait_for(lambda: [s for s in _statuses(beats) if until(s)], 3 * DISK_RECHECK_S + 10, what)[
                        -1
                    ]
                running.assert_running()
                return first[-1], last
        finally:
            regions.close()
            beats.close()
            observations.close()

    probe, _ = run_until(tmp_path / "probe", 0, None, "the bytes per view")
    per_view_mb = probe.values["disk_mb_per_view"] * 1.2  # DiskRunway's margin
    hog = tmp_path / "hog"
    fd = os.open(hog, os.O_CREAT | os.O_WRONLY)
    try:
        os.posix_fallocate(fd, 0, hog_gb * 2**30)
    finally:
        os.close(fd)
    free_mb = shutil.disk_usage(tmp_path).free / 2**20
    threshold = int((free_mb + hog_gb * 2**10 / 2) / per_view_mb)  # halfway: 2 GB of room either way
    try:
        warned, cleared = run_until(
            tmp_path / "run",
            threshold,
            lambda s: s.level == DiagnosticStatus.OK,
            "the WARN gone after space was made",
            between=hog.unlink,
        )
    finally:
        hog.unlink(missing_ok=True)
    assert warned.level == DiagnosticStatus.WARN and warned.message.startswith("disk nearly full"), warned
    assert cleared.message == "1 views in the store", cleared
    assert cleared.values["disk_views_left"] > threshold > warned.values["disk_views_left"], (warned, cleared)
