"""Copies of a run folder taken while the graph writes, and restarts from them.

At moments spread over the tiny flight every node process is frozen (SIGSTOP), the run folder
is copied and the nodes go on (SIGCONT): each copy is the folder exactly as it was at one
instant, what a crash of the whole graph at that instant leaves on a disk that had written
everything the nodes had written. (What a disk had not yet written is the other half of a
power cut: every writer fsyncs a file before renaming it into place and the folder after,
in the order checked by ``tests/storage/test_durable.py``, so a file is whole or absent.)

Each copy must read as a consistent run: no half view in the store, no view without its
photo, ``latest.json`` naming a snapshot that exists and loads, and every frame the ingest
recorded as acknowledged in the store. Then the graph restarts from each copy and finishes
the flight: every frame once, and the final map of an uninterrupted run.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time

import numpy as np
import pytest

from olsplat_nodes.launcher import Supervisor
from olsplat_nodes.scene import read_ply
from olsplat_nodes.storage import LanguageMap, ObservationStore, latest_map, load_views
from tests.helpers import free_port, wait_for

from .conftest import Background, launch_tiny, pid_of

NODES = ("ingest", "region_encoder", "accumulator", "refiner", "query_server")


def _frozen_copy(supervisor: Supervisor, run_dir, out) -> None:
    """Copy ``run_dir`` to ``out`` with every node stopped (sockets and logs left out)."""
    stopped = []
    for pid in (pid_of(supervisor, node) for node in NODES):
        try:
            if pid:
                os.kill(pid, signal.SIGSTOP)
                stopped.append(pid)
        except ProcessLookupError:  # it has just exited (the end of the flight): it writes nothing more
            pass
    try:
        shutil.copytree(run_dir, out, ignore=shutil.ignore_patterns("*.sock", "logs"))
    finally:
        for pid in stopped:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass


def _check_consistent(copy, n_gaussians: int) -> dict:
    """What a restart finds in ``copy``; AssertionError on anything half written."""
    store = ObservationStore(copy / "store", n_gaussians) if (copy / "store" / "views").is_dir() else None
    names = store.names() if store is not None else []
    if store is not None:
        segments = store.segments()
        for index in range(len(segments)):  # every visible segment whole: loads, and is not quarantined
            assert store.usable(index, segments), f"{segments[index]}: {store.quarantined}"
        assert "" not in names
    views = load_views(copy / "views")
    for view in views:  # a view's camera record exists only with its photo
        assert view.image().shape == (view.camera.height, view.camera.width, 3)
    # a view's photo and camera are saved before its segment: at most one photo ahead of the store
    assert [v.camera.name for v in views][: len(names)] == names and len(views) <= len(names) + 1
    record = latest_map(copy / "map")
    if record is not None:
        assert record["path"] == str((copy / "map" / record["file"]).resolve())  # its own, not the original's
        snapshot = LanguageMap.load(record["path"])
        assert len(snapshot.features) == n_gaussians and record["views"] <= len(names)
    state_file = copy / "ingest_acknowledged.txt"
    acknowledged = state_file.read_text().split() if state_file.exists() else []
    assert set(acknowledged) <= set(names), "the ingest recorded as acknowledged a frame the store does not hold"
    version = record["version"] if record else 0
    return {"views": len(names), "photos": len(views), "map": version, "acked": len(acknowledged)}


@pytest.mark.timeout(1500)
def test_a_run_folder_copied_mid_write_is_consistent_and_a_restart_from_it_finishes_the_flight(
    tiny,
    tmp_path,
    offline_map,
):
    scene, summary = tiny
    n_gaussians = len(read_ply(scene / "map" / "point_cloud.ply"))
    run_dir = tmp_path / "run"
    supervisor = Supervisor(launch_tiny(scene, run_dir, free_port()))
    running = Background(supervisor)
    copies = []
    try:
        wait_for(lambda: all(pid_of(supervisor, n) for n in NODES), 60, "every node started")
        views = run_dir / "store" / "views"

        def stored_now() -> int:
            return len(list(views.iterdir())) if views.is_dir() else 0

        rng = np.random.default_rng(5)
        while running.code is None and len(copies) < 8:  # copies spread over the flight
            # after the store has moved on since the last copy (up to 15 s: a loaded machine
            # flies slowly), at a random moment within a view's time, which the wait measures:
            # a fixed second let a fast machine store 7 of the tiny flight's 12 views between two
            # copies (3 copies in all)
            start = time.monotonic()
            while copies and stored_now() == copies[-1][0] and running.code is None and time.monotonic() < start + 15:
                time.sleep(0.05)
            view_time = min(1.0, max(0.05, time.monotonic() - start))
            time.sleep(float(rng.uniform(0.0, view_time)))
            if running.code is not None:
                break
            stored = stored_now()
            out = tmp_path / f"copy{len(copies)}"
            _frozen_copy(supervisor, run_dir, out)
            copies.append((stored, out))
        wait_for(lambda: running.code is not None, 480, "the launch to end after the final map")
    finally:
        supervisor.request_stop()
        running.thread.join(30)
    assert running.code == 0
    assert len(copies) >= 4 and len({stored for stored, _ in copies}) >= 3  # copies at different stages

    seen = []
    for _, copy in copies:
        state = _check_consistent(copy, n_gaussians)
        seen.append(state)
        # the graph restarts from this folder and finishes the flight
        assert Supervisor(launch_tiny(scene, copy, free_port(), "launch.compose=true")).run() == 0
        names = ObservationStore(copy / "store", 1).names()
        assert sorted(names) == sorted(set(names)) and len(names) == summary["views"], state
        record = latest_map(copy / "map")
        assert record["final"] and record["views"] == summary["views"]
        restarted = LanguageMap.load(record["path"])
        np.testing.assert_array_equal(restarted.observed, offline_map.observed)
        np.testing.assert_allclose(restarted.features, offline_map.features, atol=2e-3, rtol=0)
    print("\ncopies (stored views, photos, map version, acknowledged):", json.dumps(seen))


@pytest.mark.timeout(600)
def test_a_finished_run_launched_again_ends_with_its_final_map_unchanged(tiny, tmp_path):
    """The graph launched on a run folder whose flight had ended (every frame acknowledged, the
    final map written; a copy taken just after the end is one): it ends by itself, promptly,
    and the final map stays the one it was. (The refiner used to make one more pass that
    published the same views as not final, after the ingest had heard the final map and
    ended: the launch then waited for a final map forever.)"""
    scene, summary = tiny
    run_dir = tmp_path / "run"
    assert Supervisor(launch_tiny(scene, run_dir, free_port(), "launch.compose=true")).run() == 0
    final = latest_map(run_dir / "map")
    assert final["final"] and final["views"] == summary["views"]
    again = Background(Supervisor(launch_tiny(scene, run_dir, free_port(), "launch.compose=true")))
    try:
        wait_for(lambda: again.code is not None, 60, "the launch on the finished run to end")
    finally:
        again.supervisor.request_stop()
        again.thread.join(30)
    assert again.code == 0
    assert latest_map(run_dir / "map") == final  # the same version, file and record


@pytest.mark.timeout(900)
def test_the_refiner_killed_while_it_writes_a_snapshot_leaves_a_readable_map(
    tiny,
    tmp_path,
    offline_map,
):
    """kill -9 of the refiner while a snapshot's temporary file exists (caught by watching the
    map folder; the file still being there after the kill shows the rename had not happened):
    ``latest.json`` still names a whole snapshot, the supervisor restarts the refiner, and the
    flight ends with the map of an uninterrupted run."""
    scene, summary = tiny
    run_dir = tmp_path / "run"
    supervisor = Supervisor(launch_tiny(scene, run_dir, free_port()))
    running = Background(supervisor)
    caught = 0
    try:
        map_dir = run_dir / "map"
        wait_for(lambda: pid_of(supervisor, "refiner"), 60, "the refiner started")
        deadline = time.monotonic() + 300
        while running.code is None and not caught and time.monotonic() < deadline:
            partial = [p for p in os.scandir(map_dir) if p.name.endswith(".npz.tmp")] if map_dir.is_dir() else []
            pid = pid_of(supervisor, "refiner")
            if not partial or not pid:
                time.sleep(0.0005)
                continue
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:  # it had just exited (the final map): try the next write
                continue
            if os.path.exists(partial[0].path):  # killed before the rename: mid-write
                caught += 1
                record = latest_map(map_dir)  # what a query server would read now
                if record is not None:
                    assert LanguageMap.load(record["path"]).features.shape[0] > 0
                wait_for(lambda old=pid: pid_of(supervisor, "refiner") not in (None, old), 60, "the refiner back")
        assert caught, "no snapshot write was caught in the flight"
        wait_for(lambda: running.code is not None, 480, "the launch to end after the final map")
    finally:
        supervisor.request_stop()
        running.thread.join(30)
    assert running.code == 0
    record = latest_map(run_dir / "map")
    assert record["final"] and record["views"] == summary["views"]
    final = LanguageMap.load(record["path"])
    np.testing.assert_array_equal(final.observed, offline_map.observed)
    np.testing.assert_allclose(final.features, offline_map.features, atol=2e-3, rtol=0)
