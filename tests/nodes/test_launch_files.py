"""The shipped launch files are valid, and the ground station's monitor talks to a real query server."""

import json
import threading
from pathlib import Path

import pytest

from olsplat_nodes.launcher import load_launch, resolve_launch
from olsplat_nodes.nodes.ground_monitor import GroundMonitorNode
from olsplat_nodes.nodes.query_server import QueryServerNode
from olsplat_nodes.transport import curve
from tests.helpers import free_port, wait_for

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name", ["replay", "drone", "ground", "field_drone", "field_ground"])
def test_shipped_launch_files_validate(name, tmp_path, monkeypatch):
    # the drone files serve the ground link with CURVE from keys/ (relative to where they are
    # launched): made as their headers say, `olsplat keys generate --out keys --name drone`
    curve.generate(tmp_path / "keys", "drone")
    (tmp_path / "keys" / "allowed").mkdir()
    monkeypatch.chdir(tmp_path)
    config = load_launch(REPO / "launch" / f"{name}.yaml", run_dir=str(tmp_path))
    params = resolve_launch(config, tmp_path)
    assert set(params) == {n.name for n in config.nodes}


def test_ground_monitor_writes_the_drones_status(tiny, tmp_path):
    scene, _ = tiny
    port = free_port()
    server = QueryServerNode(
        "qs",
        {
            "map": str(scene / "map" / "point_cloud.ply"),
            "map_dir": str(tmp_path / "map"),
            "views": str(tmp_path / "views"),
            "query_endpoint": f"tcp://127.0.0.1:{port}",
            "diagnostics_bind": f"ipc://{tmp_path}/d.sock",
            "map_in": f"ipc://{tmp_path}/m.sock",
        },
    )
    status_file = tmp_path / "status.json"
    monitor = GroundMonitorNode(
        "monitor", {"connect": f"tcp://127.0.0.1:{port}", "period_s": 0.2, "status_file": str(status_file)}
    )
    stop = threading.Event()
    threads = [threading.Thread(target=node.run, args=(stop,), daemon=True) for node in (server, monitor)]
    for thread in threads:
        thread.start()
    try:
        wait_for(status_file.exists, 30, "the monitor's status file", interval_s=0.05)
        status = json.loads(status_file.read_text())
        assert status["map_version"] == 0 and status["nodes"][0]["node"] == "qs"
    finally:
        stop.set()
        for thread in threads:
            thread.join(10)
