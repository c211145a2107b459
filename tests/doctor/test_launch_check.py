"""``olsplat launch --check`` and the launch rows of ``olsplat doctor --launch``: the shipped
replay launch on the tiny flight passes and starts nothing; a missing map, a port with a
listener, a secret key others can read are blockers naming what and how to fix it."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from olsplat_nodes.launcher.preflight._launch import secret_key
from olsplat_nodes.launcher.preflight._resources import port_holder, tcp_port
from olsplat_nodes.transport import curve
from tests.helpers import free_port

from .conftest import rows_of, run_olsplat


def _endpoint(port: int) -> list[str]:
    return ["--set", f"query_server.query_endpoint=tcp://127.0.0.1:{port}"]


def test_check_of_the_replay_launch_passes_and_starts_nothing(tmp_path, replay_sets):
    run_dir = tmp_path / "run"
    done = run_olsplat("launch", "--check", "replay", "--run-dir", str(run_dir), *replay_sets,
                       *_endpoint(free_port()), cwd=tmp_path)  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    names = [line.split()[0] for line in done.stdout.splitlines()[2:-1] if not line.startswith(" ")]
    assert names[:2] == ["launch", "memory"] and "disk" in names and "port" in names, done.stdout
    assert done.stdout.splitlines()[-1].endswith("0 blocker: ready")
    assert not run_dir.exists()  # no logs, no sockets, no store: nothing was started


def test_check_names_a_missing_map(tmp_path, replay_sets):
    missing = tmp_path / "nowhere" / "point_cloud.ply"
    sets = [
        *replay_sets,
        *(w for n in ("query_server", "accumulator", "refiner") for w in ("--set", f"{n}.map={missing}")),
    ]
    done = run_olsplat("launch", "--check", "replay", "--run-dir", str(tmp_path / "run"), *sets,
                       *_endpoint(free_port()), cwd=tmp_path)  # fmt: skip
    assert done.returncode == 1
    line = next(line for line in done.stdout.splitlines() if line.startswith("input map"))
    assert "blocker" in line and str(missing) in line and "no such file" in line
    assert not (tmp_path / "run").exists()


def test_a_ros2_bag_as_the_replay_source_is_checked_as_a_bag(tmp_path, tiny, replay_sets):
    """A rosbag2 folder is a bag, not an image folder without a COLMAP model; a broken one is a
    blocker naming it."""
    from olsplat_nodes.sources.replay_log import read_replay
    from olsplat_nodes.sources.rosbag_write import write_rosbag2

    scene, summary = tiny
    bag, broken = tmp_path / "flight_bag", tmp_path / "broken_bag"
    write_rosbag2(bag, read_replay(scene / "replay.mcap"))
    broken.mkdir()
    (broken / "metadata.yaml").write_text("not: [a bag")
    rows = {}
    for source in (bag, broken):
        done = run_olsplat("launch", "--check", "replay", "--run-dir", str(tmp_path / "run"), *replay_sets,
                           "--set", f"ingest.source={source}", *_endpoint(free_port()), cwd=tmp_path)  # fmt: skip
        rows[source] = (done.returncode, next(ln for ln in done.stdout.splitlines() if ln.startswith("input replay")))
    code, line = rows[bag]
    assert code == 0 and " ok " in line and "ROS 2 bag (mcap)" in line, line
    assert f"/camera/image/compressed {summary['views']}" in line
    code, line = rows[broken]
    assert code == 1 and "blocker" in line and str(broken) in line and "cannot open the bag" in line, line


def test_a_port_with_a_listener_is_a_blocker_naming_the_process(tmp_path, replay_sets):
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        json_file = tmp_path / "d.json"
        done = run_olsplat("doctor", "--launch", "replay", "--run-dir", str(tmp_path / "run"), *replay_sets,
                           *_endpoint(port), "--json", str(json_file), cwd=tmp_path)  # fmt: skip
        row = rows_of(json_file)[f"port {port}"]
        assert done.returncode == 1
        assert row["status"] == "blocker" and "in use" in row["figure"] and f"pid {os.getpid()}" in row["figure"]
        assert "query_server.query_endpoint" in row["fix"]
        assert (port_holder(port) or "").startswith(f"pid {os.getpid()} ")
    assert tcp_port(f"tcp://127.0.0.1:{port}", "x.y").status == "ok"  # closed: free again


def test_a_secret_key_others_can_read_is_a_blocker(tmp_path):
    public, secret = curve.generate(tmp_path / "keys", "ground")
    curve.generate(tmp_path / "keys", "drone")
    assert secret_key(secret, "monitor.client_secret").status == "ok"
    os.chmod(secret, 0o644)
    row = secret_key(secret, "monitor.client_secret")
    assert row.status == "blocker" and "0644" in row.figure and row.fix == f"chmod 600 {secret}"
    assert secret_key(public, "monitor.client_secret").status == "blocker"  # a public file given as the secret
    # through the ground station's launch: the row names the param and the fix
    done = run_olsplat("launch", "--check", "ground", "--run-dir", str(tmp_path / "run"),
                       "--set", f"monitor.client_secret={secret}",
                       "--set", f"monitor.server_public={tmp_path / 'keys' / 'drone.key'}", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 1, done.stdout + done.stderr
    line = next(line for line in done.stdout.splitlines() if line.startswith("key monitor.client_secret"))
    assert "blocker" in line and "mode 0644" in line
    assert f"chmod 600 {secret}" in done.stdout
    os.chmod(secret, 0o600)
    again = run_olsplat("launch", "--check", "ground", "--run-dir", str(tmp_path / "run"),
                        "--set", f"monitor.client_secret={secret}",
                        "--set", f"monitor.server_public={tmp_path / 'keys' / 'drone.key'}", cwd=tmp_path)  # fmt: skip
    assert again.returncode == 0, again.stdout + again.stderr


def test_a_query_server_key_others_can_read_stops_the_launch_check(tmp_path, replay_sets):
    _, secret = curve.generate(tmp_path / "keys", "drone")
    (tmp_path / "keys" / "allowed").mkdir()
    os.chmod(secret, 0o644)
    done = run_olsplat("launch", "--check", "replay", "--run-dir", str(tmp_path / "run"), *replay_sets,
                       *_endpoint(free_port()), "--set", f"query_server.server_secret={secret}",
                       "--set", f"query_server.allow_dir={tmp_path / 'keys' / 'allowed'}", cwd=tmp_path)  # fmt: skip
    assert done.returncode == 1
    assert "blocker" in done.stdout and str(secret) in done.stdout and "chmod 600" in done.stdout
    assert Path(secret).stat().st_mode & 0o777 == 0o644  # reported, not changed
