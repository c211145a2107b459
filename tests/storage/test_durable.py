"""What a power cut can take: nothing acknowledged. Every writer of a run's folder fsyncs each
file before renaming it into place and fsyncs the folder after the rename (``durable.py``).
The real fsync and rename run; the test only records their order."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from olsplat_nodes.durable import append_line
from olsplat_nodes.storage import LanguageMap, ObservationStore, save_view, write_snapshot
from tests.aggregate.test_refine_store import _views

from ..conftest import camera_for


@pytest.fixture
def events(monkeypatch):
    """[("fsync", path) | ("rename", destination)] in the order the process made them."""
    log: list[tuple[str, str]] = []
    real_fsync, real_rename, real_replace = os.fsync, os.rename, os.replace

    def fsync(fd):
        log.append(("fsync", os.path.realpath(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def rename(src, dst, *args, **kwargs):
        real_rename(src, dst, *args, **kwargs)
        log.append(("rename", os.path.realpath(dst)))

    def replace(src, dst, *args, **kwargs):
        real_replace(src, dst, *args, **kwargs)
        log.append(("rename", os.path.realpath(dst)))

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "rename", rename)
    monkeypatch.setattr(os, "replace", replace)
    return log


def _durable(log, final: Path, written_as: Path) -> None:
    """``final`` came from ``written_as`` fsynced, then renamed, then its folder fsynced."""
    order = [(kind, Path(path)) for kind, path in log]
    synced = order.index(("fsync", written_as.resolve()))
    renamed = order.index(("rename", final.resolve()))
    folder = [i for i, e in enumerate(order) if e == ("fsync", final.parent.resolve()) and i > renamed]
    assert synced < renamed and folder, (final, order)


def test_a_store_segment_is_durable_before_append_returns(tmp_path, events):
    store = ObservationStore(tmp_path / "store", 150, writer=True)
    name, obs, bank = next(_views(1, 150))
    store.append(name, obs, bank)
    segment = tmp_path / "store" / "views" / "000000"
    tmp = segment.with_name("000000.tmp")
    order = [(kind, Path(path)) for kind, path in events]
    renamed = order.index(("rename", segment.resolve()))
    for file in sorted(segment.iterdir()):  # every file fsynced (under the temp name) before the rename
        assert order.index(("fsync", (tmp / file.name).resolve())) < renamed, file.name
    assert order.index(("fsync", tmp.resolve())) < renamed  # the segment's entries
    assert ("fsync", segment.parent.resolve()) in order[renamed:]  # the rename


def test_views_snapshots_and_acknowledgements_are_durable(tmp_path, events):
    camera = camera_for("PINHOLE_CENTRED", 40, 30)
    save_view(tmp_path / "views", 0, camera, np.zeros((30, 40, 3), np.uint8))
    _durable(events, tmp_path / "views" / "000000.jpg", tmp_path / "views" / "000000.jpg.tmp")
    _durable(events, tmp_path / "views" / "000000.json", tmp_path / "views" / "000000.json.tmp")
    photo = [e for e in events if e[0] == "rename"]
    assert photo[0][1].endswith(".jpg") and photo[1][1].endswith(".json")  # the record last

    language_map = LanguageMap.from_features(np.ones((5, 4), np.float32), np.ones(5, bool), "enc")
    write_snapshot(tmp_path / "map", 1, language_map, {"views": 1}, None)
    snapshot = tmp_path / "map" / "language_map_000001.npz"
    _durable(events, snapshot, snapshot.with_name(snapshot.name + ".tmp"))
    _durable(events, tmp_path / "map" / "latest.json", tmp_path / "map" / "latest.json.tmp")
    renames = [Path(p).name for kind, p in events if kind == "rename"]
    assert renames.index("latest.json") > renames.index(snapshot.name)  # never pointing at a missing file
    assert LanguageMap.load(snapshot).features.shape == (5, 4)

    (tmp_path / "acks").mkdir()
    events.clear()
    append_line(tmp_path / "acks" / "acknowledged.txt", "frame_0000.jpg")
    assert ("fsync", str((tmp_path / "acks" / "acknowledged.txt").resolve())) in events
    assert ("fsync", str((tmp_path / "acks").resolve())) in events  # a new file: its folder entry too


_FULL_DISK = """
import resource, signal, sys
from pathlib import Path
from olsplat_nodes.storage import ObservationStore
from tests.aggregate.test_refine_store import _views

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
folder = Path(sys.argv[1])
store = ObservationStore(folder, 150, writer=True)
(name, obs, bank), = _views(1, 150)
soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
resource.setrlimit(resource.RLIMIT_FSIZE, (256, hard))  # no file may grow past 256 bytes: as a full disk
try:
    store.append(name, obs, bank)
except OSError as exc:
    print("ERROR", exc.filename, "|", exc.strerror)
print("LEFT", sorted(p.name for p in (folder / "views").iterdir()))
resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))  # room again: the same view goes in
print("INDEX", store.append(name, obs, bank))
print("LEFT", sorted(p.name for p in (folder / "views").iterdir()))
"""


def test_a_view_that_cannot_be_written_is_one_error_and_leaves_no_half_segment(tmp_path):
    """A store write that fails part-way (the operating system refuses to grow a file, as on a
    full disk) raises one OSError naming the store and the view, removes the half-written
    segment, and the next append, once there is room, takes the same index."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", _FULL_DISK, str(tmp_path / "store")],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    error = next(line for line in lines if line.startswith("ERROR"))
    assert str(tmp_path / "store") in error and "could not be written" in error and "MB free on its disk" in error
    assert lines[lines.index(error) + 1] == "LEFT []"
    assert lines[-2:] == ["INDEX 0", "LEFT ['000000']"]


def test_a_views_segment_bytes_are_its_arrays(tmp_path):
    """``segment_bytes`` (what a run's disk estimate counts) is the bytes of the arrays the
    store writes for the view."""
    from olsplat_nodes.storage.store import segment_bytes

    store = ObservationStore(tmp_path / "store", 150, writer=True)
    for name, obs, bank in _views(2, 150):
        index = store.append(name, obs, bank)
        segment = tmp_path / "store" / "views" / f"{index:06d}"
        assert segment_bytes(obs, bank) == sum(np.load(f).nbytes for f in segment.glob("*.npy"))


def test_a_run_that_will_not_fit_on_its_disk_is_told_early():
    """The warning an offline run logs at its checkpoints: none while the views left fit, with
    a margin of 20 %; otherwise one line with the folder, the need, the rate and the space."""
    from olsplat_nodes.pipeline.offline import disk_warning

    mb = 2**20
    assert disk_warning(Path("run"), written=5 * 10 * mb, done=5, total=105, free=1200 * mb) is None
    warning = disk_warning(Path("run"), written=5 * 10 * mb, done=5, total=105, free=1199 * mb)
    assert warning is not None and warning.startswith("run: the store will need ~1.2 GB more for the 100 views left")
    assert "(10.0 MB per view so far)" in warning and "1.2 GB free" in warning


def test_a_disk_runway_counts_the_views_the_free_space_holds_at_the_rate_so_far():
    """None before the first view; then free / (bytes per view x the 20 % margin)."""
    from olsplat_nodes.durable import DiskRunway

    runway = DiskRunway()
    assert runway.bytes_per_view is None and runway.views_left(10**9) is None
    runway.add(4 * 2**20)
    runway.add(6 * 2**20)
    assert runway.bytes_per_view == 5 * 2**20
    assert runway.views_left(600 * 2**20) == pytest.approx(100.0)
    assert DiskRunway(margin=1.0, written=10, views=1).views_left(25) == pytest.approx(2.5)


def test_the_map_history_keeps_every_version_in_order_and_skips_a_torn_line(tmp_path):
    from olsplat_nodes.storage import map_history

    assert map_history(tmp_path / "map") == []
    language_map = LanguageMap.from_features(np.ones((5, 4), np.float32), np.ones(5, bool), "enc")
    for version in range(1, 6):  # more versions than the folder keeps snapshots of
        write_snapshot(tmp_path / "map", version, language_map, {"views": version, "exact": version % 2 == 1}, None)
    history = map_history(tmp_path / "map")
    assert [r["version"] for r in history] == [1, 2, 3, 4, 5] and [r["views"] for r in history] == [1, 2, 3, 4, 5]
    assert [r["exact"] for r in history] == [True, False, True, False, True]
    assert all(r["file"] == f"language_map_{r['version']:06d}.npz" and "path" not in r for r in history)
    assert len(list((tmp_path / "map").glob("language_map_*.npz"))) == 3  # the snapshots are pruned, the history not
    with open(tmp_path / "map" / "versions.jsonl", "a") as torn:
        torn.write('{"version": 6, "vie')  # a power cut in the middle of a line
    assert [r["version"] for r in map_history(tmp_path / "map")] == [1, 2, 3, 4, 5]
