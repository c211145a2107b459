"""A launcher an operator can trust (issue 42): nodes die with their launcher, a launch refuses a
port or a run folder another graph holds, a node that fails on its input is not restarted and
ends the launch with its reason, a crashing node is restarted with a growing delay and then
given up (the launch ends non-zero, never hangs), and a restarted node says so in its status.
Real launcher and node processes throughout."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from olsplat_nodes.errors import EXIT_BAD_INPUT, EXIT_CONFIG
from olsplat_nodes.launcher import load_launch
from olsplat_nodes.transport.diagnostics import DiagnosticsCollector
from tests.helpers import free_port, wait_for

from .conftest import NODES, REPO, run_launch, write_launch

pytestmark = pytest.mark.timeout(300)

OLSPLAT = Path(sys.executable).with_name("olsplat")


def running(pid: int) -> bool:
    """Whether ``pid`` is a live process: any of its threads not a zombie. A zombie nobody has
    reaped yet is not live (an orphan's new parent may be slow to reap it); but a killed
    process's main thread turns zombie before its other threads (numba, ZeroMQ) have exited, and
    until the last one has, the process still holds its sockets."""
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return False
    for task in tasks:
        try:
            state = (task / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if state not in ("Z", "X"):
            return True
    return False


def launch(path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([str(OLSPLAT), "launch", str(path), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO)  # fmt: skip


def node_pids(launch_log: Path) -> dict[str, int]:
    """The pid each node was last started with, from the launch's status lines."""
    pids = {}
    for line in launch_log.read_text().splitlines() if launch_log.exists() else []:
        if ": started (pid " in line:
            name = line.split("] ", 1)[1].split(": started", 1)[0]
            pids[name] = int(line.rsplit("pid ", 1)[1].rstrip(")"))
    return pids


def kill_launcher_and_check(launcher: subprocess.Popen, pids: list[int]) -> None:
    """SIGKILL the launcher; no node process may be left after 2 s."""
    assert all(running(pid) for pid in pids)
    launcher.kill()
    launcher.wait(10)
    deadline = time.monotonic() + 2.0
    while [pid for pid in pids if running(pid)] and time.monotonic() < deadline:
        time.sleep(0.02)
    left = [pid for pid in pids if running(pid)]
    for pid in left:  # do not leave ghosts to the next test
        os.kill(pid, signal.SIGKILL)
    assert left == [], f"nodes still running 2 s after the launcher was killed: {left}"


# --- nodes die with their launcher ---------------------------------------------------------------


def test_killing_the_launcher_stops_every_node_within_2_s(tmp_path):
    names = ["a", "b"]
    path = write_launch(tmp_path, [
        {"name": name, "exec": f"{NODES}:Waiter", "params": {"pid_file": "{run_dir}/{name}.pid"}} for name in names
    ])  # fmt: skip
    launcher = launch(path)
    try:
        files = [tmp_path / "run" / f"{name}.pid" for name in names]
        pids = wait_for(lambda: all(f.exists() for f in files) and [int(f.read_text()) for f in files], 30, "nodes")
        kill_launcher_and_check(launcher, pids)
    finally:
        launcher.kill()
        launcher.communicate()
    # the lock of the killed launcher is no lock: the same run folder launches again
    again = subprocess.run(
        [str(OLSPLAT), "launch", str(path), "--set", f"a.release_file={files[0]}", "--set",
         f"b.release_file={files[1]}", "--set", "launch.exit_when=[a, b]"],
        capture_output=True, text=True, cwd=REPO, timeout=60,
    )  # fmt: skip
    assert again.returncode == 0, again.stdout + again.stderr


def tiny_flight(scene: Path, port: int) -> list[str]:
    """``--set`` options of the shipped replay graph over the tiny flight, at one frame a second
    (the graph is still flying when the test acts on it), the query server on ``port``."""
    ply = scene / "map" / "point_cloud.ply"
    sets = [f"ingest.source={scene / 'replay.mcap'}", "ingest.fast=false", "ingest.rate_hz=1",
            f"query_server.map={ply}", f"accumulator.map={ply}", f"refiner.map={ply}",
            f"query_server.query_endpoint=tcp://127.0.0.1:{port}", "refiner.period_s=2"]  # fmt: skip
    return [arg for item in sets for arg in ("--set", item)]


def test_the_shipped_replay_graph_dies_with_its_launcher_and_a_restarted_node_says_so(tmp_path, tiny):
    """The five real nodes: kill -9 of one is a restart that ``olsplat ground status`` shows;
    kill -9 of the launcher leaves no node running (none keeps the query port)."""
    scene, _ = tiny
    port, run = free_port(), tmp_path / "run"
    nodes = ["query_server", "ingest", "region_encoder", "accumulator", "refiner"]
    launcher = launch("replay", "--run-dir", str(run), *tiny_flight(scene, port))
    logs = run / "logs"

    def ready(name: str, times: int = 1) -> bool:
        log = logs / f"{name}.log"
        return log.exists() and log.read_text().count(f"{name} ready:") >= times

    try:
        wait_for(lambda: all(ready(n) for n in nodes), 180, "the five nodes ready", interval_s=0.2)
        victim = node_pids(logs / "launch.log")["region_encoder"]
        os.kill(victim, signal.SIGKILL)
        wait_for(lambda: ready("region_encoder", 2), 120, "the region encoder restarted", interval_s=0.2)

        def status() -> dict:
            done = subprocess.run([str(OLSPLAT), "ground", "status", "--json", "--connect", f"tcp://127.0.0.1:{port}"],
                                  capture_output=True, text=True, timeout=60)  # fmt: skip
            nodes_ = json.loads(done.stdout)["nodes"] if done.returncode == 0 else []
            return next((n["values"] for n in nodes_ if n["node"] == "region_encoder"), {})

        values = wait_for(lambda: status().get("restarts", 0) >= 1 and status(), 60, "restarts in the status")
        assert values["restarts"] == 1 and values["last_exit"] == "killed by SIGKILL", values
        table = subprocess.run([str(OLSPLAT), "ground", "status", "--connect", f"tcp://127.0.0.1:{port}"],
                               capture_output=True, text=True, timeout=60).stdout  # fmt: skip
        line = next(line for line in table.splitlines() if line.strip().startswith("region_encoder"))
        assert "[restarts 1, last exit: killed by SIGKILL]" in line, table
        assert launcher.poll() is None, "the flight ended before the test could kill the launcher"
        pids = node_pids(logs / "launch.log")
        assert sorted(pids) == sorted(nodes)
        kill_launcher_and_check(launcher, list(pids.values()))
    finally:
        launcher.kill()
        launcher.communicate()
    with socket.socket() as probe:  # nobody holds the query port any more
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind(("127.0.0.1", port))


# --- a launch refuses what another graph holds --------------------------------------------------


def test_a_launch_onto_a_held_port_is_refused_in_one_line(tmp_path, tiny):
    scene, _ = tiny
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        run = tmp_path / "run"
        done = subprocess.run([str(OLSPLAT), "launch", "replay", "--run-dir", str(run), *tiny_flight(scene, port)],
                              capture_output=True, text=True, cwd=REPO, timeout=120)  # fmt: skip
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"olsplat launch: error: port {port}: "), lines
    assert f"tcp://127.0.0.1:{port} is in use by pid {os.getpid()}" in lines[0]
    assert "query_server.query_endpoint" in lines[0]
    assert not (run / "logs").exists()  # no node started


def test_a_node_whose_endpoint_is_taken_meanwhile_fails_on_configuration_without_restarts(tmp_path):
    """A bind that fails on "Address already in use" in the node itself (an endpoint the
    pre-flight check does not know, or one taken between the check and the bind) is the
    environment's fault, not a crash: exit code 78, its one line on the console, no restart."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        path = write_launch(tmp_path, [
            {"name": "other", "exec": f"{NODES}:Waiter"},
            {"name": "talker", "exec": f"{NODES}:Talker", "params": {"endpoint": f"tcp://127.0.0.1:{port}"}},
        ])  # fmt: skip
        code, out = run_launch(load_launch(path), timeout_s=60)
    assert code == EXIT_CONFIG, out
    assert f"talker: cannot bind tcp://127.0.0.1:{port}: Address already in use" in out
    assert "restarting" not in out and "other: stopped" in out
    log = (tmp_path / "run" / "logs" / "talker.log").read_text()
    assert log.count("olsplat launch: start #") == 1 and "Traceback" not in log
    assert f"node talker: error: cannot bind tcp://127.0.0.1:{port}" in log


def test_a_launch_into_a_run_folder_held_by_a_running_graph_is_refused_in_one_line(tmp_path):
    path = write_launch(tmp_path, [{"name": "a", "exec": f"{NODES}:Waiter", "params": {"pid_file": "{run_dir}/a.pid"}}])
    first = launch(path)
    try:
        wait_for(lambda: (tmp_path / "run" / "a.pid").exists(), 30, "the first graph")
        second = subprocess.run([str(OLSPLAT), "launch", str(path)], capture_output=True, text=True, cwd=REPO,
                                timeout=60)  # fmt: skip
        assert first.poll() is None
    finally:
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=30)
    assert second.returncode == 1, second.stdout + second.stderr
    run = tmp_path / "run"
    assert second.stderr.strip().splitlines() == [
        f"olsplat launch: error: run folder {run} is in use by another launch (pid {first.pid}, "
        f"{run / 'launch.lock'}): stop that launch, or use another --run-dir"
    ]
    assert second.stdout == ""


def test_a_stale_lock_file_of_a_dead_launcher_is_no_lock(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "launch.lock").write_text(f"{dead.pid}\n")
    path = write_launch(tmp_path, [{"name": "t", "exec": f"{NODES}:Ticker"}], exit_when=["t"])
    code, out = run_launch(load_launch(path))
    assert code == 0, out


# --- failures classified ---------------------------------------------------------------------------


def truncated(ply: Path, out: Path) -> Path:
    data = ply.read_bytes()
    out.write_bytes(data[: len(data) * 2 // 3])
    return out


def with_nan_positions(ply: Path, out: Path) -> Path:
    from olsplat_nodes.scene.ply import read_ply, write_ply

    gaussians = read_ply(ply)
    gaussians.means[::7] = np.nan
    write_ply(out, gaussians)
    return out


@pytest.mark.parametrize("corrupt", [truncated, with_nan_positions])
def test_a_corrupt_map_ends_the_launch_with_the_reason_and_no_restart(tmp_path, tiny, corrupt):
    scene, _ = tiny
    bad = corrupt(scene / "map" / "point_cloud.ply", tmp_path / "bad.ply")
    run = tmp_path / "run"
    sets = [f"--set={node}.map={bad}" for node in ("query_server", "accumulator", "refiner")]
    done = subprocess.run(
        [str(OLSPLAT), "launch", "replay", "--run-dir", str(run), *tiny_flight(scene, free_port()), *sets],
        capture_output=True, text=True, cwd=REPO, timeout=240,
    )  # fmt: skip
    out = done.stdout
    assert done.returncode == EXIT_BAD_INPUT, out + done.stderr
    failed = [line for line in out.splitlines() if f": {bad}: " in line]
    assert failed, out  # NODE: /path/bad.ply: what is wrong with it
    name = failed[0].split("] ", 1)[1].split(":", 1)[0]
    assert name in ("query_server", "accumulator", "refiner")
    assert "restarting" not in out and "launch failed: " + name + " failed on its bad input (exit code 65)" in out
    log = (run / "logs" / f"{name}.log").read_text()
    assert log.count("olsplat launch: start #") == 1 and "Traceback" not in log
    assert f"node {name}: error: {bad}: " in log
    for other in run.glob("logs/*.log"):
        assert other.read_text().count("olsplat launch: start #") <= 1, other


def test_a_crashing_node_is_restarted_with_a_growing_delay_then_given_up_and_the_launch_fails(tmp_path):
    starts = tmp_path / "starts.txt"
    path = write_launch(tmp_path, [
        {"name": "steady", "exec": f"{NODES}:Waiter"},  # runs for ever: the launch must not wait on it
        {"name": "crasher", "exec": f"{NODES}:Crasher", "max_restarts": 3, "restart_delay_s": 0.5,
         "params": {"starts_file": str(starts)}},
    ])  # fmt: skip
    code, out = run_launch(load_launch(path), timeout_s=90)
    assert code == 1, out
    for delay, n in ((0.5, 1), (1, 2), (2, 3)):
        assert f"crasher: restarting in {delay:g} s (restart {n} of 3)" in out
    assert "crasher: giving up after 3 restarts (max_restarts: 3)" in out
    assert "launch failed: crasher gave up after 3 restarts; stopping the rest" in out and "steady: stopped" in out
    starts_and_crashes = np.array([[float(t) for t in line.split()] for line in starts.read_text().splitlines()])
    # from a crash to the next process's fork: the delay, plus the exit and its noticing (which a
    # busy machine lengthens, never shortens); the interpreter's start is not in it. Waits of at
    # least 0.5, 1 and 2 s cannot come from a launcher that waits one fixed delay of 0.5 s.
    waits = starts_and_crashes[1:, 0] - starts_and_crashes[:-1, 1]
    assert starts_and_crashes.shape == (4, 2) and (waits >= np.array([0.5, 1.0, 2.0]) - 0.02).all(), waits
    log = (tmp_path / "run" / "logs" / "crasher.log").read_text()
    assert log.count("RuntimeError: crasher crashes on purpose") == 4  # crashes keep their tracebacks


@pytest.mark.parametrize("compose", [False, True])
def test_a_restarted_node_reports_its_restarts_and_last_exit_in_its_heartbeat(tmp_path, compose):
    context = zmq.Context()
    collector = DiagnosticsCollector(context, "tcp://127.0.0.1:*")
    try:
        path = write_launch(tmp_path, [
            {"name": "beater", "exec": f"{NODES}:Beater", "restart_delay_s": 0.05,
             "params": {"diagnostics": collector.endpoint, "crash_once": "{run_dir}/crashed"}},
        ], compose=compose)  # fmt: skip
        from .conftest import Running

        launched = Running(load_launch(path))
        try:

            def restarted() -> dict:
                collector.poll(50)
                values = next((n["values"] for n in collector.nodes() if n["node"] == "beater"), {})
                return values if values.get("restarts", 0) >= 1 else {}

            values = wait_for(restarted, 60, "a heartbeat of the restarted node", interval_s=0)
        finally:
            launched.supervisor.request_stop()
            launched.wait()
    finally:
        collector.close()
        context.destroy(linger=0)
    assert values["restarts"] == 1 and values["last_exit"] == "exited with code 3", values
