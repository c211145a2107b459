"""A run records its prior map (``STORE/prior_map.json``: absolute path and SHA-256), so that
``olsplat ground web --run DIR`` finds the map without ``--map`` wherever the run folder lies;
a map that is gone or changed is one line asking for ``--map``."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.storage.prior import PRIOR_FILE, record_prior_map, recorded_prior_map
from tests.helpers import free_port

pytestmark = pytest.mark.timeout(120)


def test_the_record_names_the_map_and_a_changed_or_gone_map_is_refused(tmp_path):
    ply = tmp_path / "maps" / "prior.ply"
    ply.parent.mkdir()
    ply.write_bytes(b"ply\n" + bytes(range(256)) * 4000)
    store = tmp_path / "store"
    store.mkdir()
    assert recorded_prior_map(store) is None  # no record: the caller's fallback
    record = record_prior_map(store, ply)
    saved = json.loads((store / PRIOR_FILE).read_text())
    assert saved["path"] == str(ply.resolve()) and saved["sha256"] == hashlib.sha256(ply.read_bytes()).hexdigest()
    assert saved["bytes"] == ply.stat().st_size and record.sha256 == saved["sha256"]
    assert recorded_prior_map(store) == ply.resolve()

    data = bytearray(ply.read_bytes())
    data[100] ^= 0xFF  # same size, other bytes
    ply.write_bytes(bytes(data))
    with pytest.raises(OlsplatInputError, match="has changed since") as changed:
        recorded_prior_map(store)
    assert str(ply.resolve()) in str(changed.value) and "--map" in str(changed.value)
    ply.unlink()
    with pytest.raises(OlsplatInputError, match="which is gone") as gone:
        recorded_prior_map(store)
    assert "--map" in str(gone.value) and "\n" not in str(gone.value)


def test_ground_web_finds_the_recorded_map_of_a_run_folder_anywhere(tiny, tiny_run, tmp_path, capsys):
    """The run folder copied away from its flight (no ../flight/): the page serves from the
    recorded map; with the map changed it refuses in one line that asks for --map."""
    scene, _ = tiny
    ply = tmp_path / "elsewhere" / "point_cloud.ply"
    ply.parent.mkdir()
    shutil.copy(scene / "map" / "point_cloud.ply", ply)
    run = tmp_path / "runs" / "2024-flight"
    shutil.copytree(tiny_run, run)
    args = ["ground", "web", "--run", str(run), "--port", str(free_port()), "--seconds", "0.5"]

    assert main(args) == 1  # no record, no ../flight/: the old default is not there
    assert "--map" in capsys.readouterr().err

    record_prior_map(run / "store", ply)  # as the accumulator does
    # served in its own process, as the user runs it (viser warns of its own deprecations in-process)
    served = subprocess.run(
        [str(Path(sys.executable).parent / "olsplat"), *args], capture_output=True, text=True, timeout=90
    )
    assert served.returncode == 0 and "ground station: http://" in served.stdout, served.stdout + served.stderr

    with open(ply, "ab") as stream:  # the map was edited since the run
        stream.write(b"\0")
    assert main(args) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "has changed since" in err and "--map" in err, err
