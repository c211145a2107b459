"""The supervisor with real child processes and threads: exit_when, restarts after a crash and
after kill -9, giving up, per-node logs, and a composed (inproc) graph."""

from __future__ import annotations

import os
import signal

import pytest

from olsplat_nodes.launcher import load_launch
from tests.helpers import wait_for

from .conftest import NODES, Running, run_launch, write_launch


def read_logs(tmp_path) -> dict[str, str]:
    return {p.stem: p.read_text() for p in (tmp_path / "run" / "logs").glob("*.log")}


@pytest.mark.parametrize("compose", [False, True])
def test_exit_when_node_finishing_ends_the_launch_and_stops_the_rest(tmp_path, compose):
    path = write_launch(tmp_path, [
        {"name": "forever", "exec": f"{NODES}:Waiter", "params": {"pid_file": "{run_dir}/{name}.pid"}},
        {"name": "ticker", "exec": f"{NODES}:Ticker", "params": {"ticks": 3, "wait_for": "{run_dir}/forever.pid"}},
    ], exit_when=["ticker"], compose=compose)  # fmt: skip  # the ticker ends only once "forever" is up
    code, out = run_launch(load_launch(path))
    assert code == 0, out
    assert "ticker: exited with code 0" in out and "exit_when nodes finished (ticker); stopping the rest" in out
    assert "forever: stopped (exited with code 0)" in out  # stopped by SIGTERM / its stop event, cleanly
    logs = read_logs(tmp_path)
    assert set(logs) == {"launch", "forever", "ticker"}
    assert "ticker tick 2" in logs["ticker"] and "start #1 of node ticker" in logs["ticker"]
    assert "forever waiting" in logs["forever"] and "forever stopped" in logs["forever"]
    assert "ticker tick" not in logs["forever"]  # composed: each node's records in its own log
    assert logs["launch"].splitlines()[-1] == out.splitlines()[-1]


@pytest.mark.parametrize(("compose", "how"), [(False, "exit"), (False, "raise"), (True, "raise"), (True, "exit")])
def test_a_node_that_crashes_once_is_restarted_and_then_finishes(tmp_path, compose, how):
    path = write_launch(tmp_path, [
        {"name": "flaky", "exec": f"{NODES}:Ticker", "restart_delay_s": 0.05,
         "params": {"crash_once": "{run_dir}/crashed", "crash_how": how}},
    ], exit_when=["flaky"], compose=compose)  # fmt: skip
    code, out = run_launch(load_launch(path))
    assert code == 0, out
    failed = "raised RuntimeError: flaky crashes on purpose" if how == "raise" and compose else "exited with code"
    assert f"flaky: {failed}" in out and "flaky: restarting in 0.05 s (restart 1 of 5)" in out
    log = read_logs(tmp_path)["flaky"]
    assert "start #1 of node flaky" in log and "start #2 of node flaky" in log and "flaky tick 2" in log
    if how == "raise":  # the traceback is in the node's log, in both modes
        assert "Traceback" in log and "RuntimeError: flaky crashes on purpose" in log


def test_kill_9_of_a_running_child_is_noticed_and_the_node_restarted(tmp_path):
    run = tmp_path / "run"
    path = write_launch(tmp_path, [
        {"name": "victim", "exec": f"{NODES}:Waiter", "restart_delay_s": 0.05,
         "params": {"pid_file": "{run_dir}/victim.pid", "release_file": "{run_dir}/release"}},
    ], exit_when=["victim"])  # fmt: skip
    running = Running(load_launch(path))
    pid_file = run / "victim.pid"
    first = int(wait_for(lambda: pid_file.exists() and pid_file.read_text(), 10.0, "victim's pid file"))
    assert running.supervisor.pids == {"victim": first}
    os.kill(first, signal.SIGKILL)
    second = int(
        wait_for(lambda: pid_file.read_text() != str(first) and pid_file.read_text(), 10.0, "a restarted victim")
    )
    assert second != first
    (run / "release").touch()
    assert running.wait() == 0
    out = running.out.getvalue()
    assert "victim: killed by SIGKILL" in out and "victim: restarting" in out
    assert out.count("victim: started (pid") == 2


def test_max_restarts_exhausted_on_an_exit_when_node_fails_the_launch(tmp_path):
    path = write_launch(tmp_path, [
        {"name": "other", "exec": f"{NODES}:Waiter"},
        {"name": "broken", "exec": f"{NODES}:Ticker", "max_restarts": 2, "restart_delay_s": 0.0,
         "params": {"ticks": 0, "exit_code": 4}},
    ], exit_when=["broken"])  # fmt: skip
    code, out = run_launch(load_launch(path))
    assert code == 1, out
    assert out.count("broken: exited with code 4") == 3
    assert "broken: giving up after 2 restarts (max_restarts: 2)" in out
    assert "launch failed: broken is in exit_when" in out and "other: stopped" in out
    assert out == read_logs(tmp_path)["launch"]  # every status line is also in launch.log
    assert read_logs(tmp_path)["broken"].count("olsplat launch: start #") == 3


def test_giving_up_on_a_node_outside_exit_when_lets_the_launch_go_on(tmp_path):
    path = write_launch(tmp_path, [
        {"name": "broken", "exec": f"{NODES}:Ticker", "restart": "never", "params": {"ticks": 0, "exit_code": 4}},
        {"name": "slow", "exec": f"{NODES}:Ticker", "params": {"ticks": 20, "period_s": 0.02}},
    ], exit_when=["slow"])  # fmt: skip
    code, out = run_launch(load_launch(path))
    assert code == 0, out
    assert "broken: not restarted (restart: never)" in out and "slow: exited with code 0" in out


def test_without_exit_when_the_launch_ends_when_every_node_has_ended(tmp_path):
    path = write_launch(tmp_path, [
        {"name": "a", "exec": f"{NODES}:Ticker", "restart": "always", "max_restarts": 1, "restart_delay_s": 0.0},
        {"name": "b", "exec": f"{NODES}:Ticker", "restart": "never", "params": {"exit_code": 1}},
    ])  # fmt: skip
    code, out = run_launch(load_launch(path))
    assert code == 1, out  # b failed
    assert out.count("a: started") == 2 and "a: giving up after 1 restarts" in out
    assert "every node has ended; failed: a, b" in out


def test_a_node_that_ignores_sigterm_is_killed_after_the_grace_period(tmp_path):
    path = write_launch(tmp_path, [
        {"name": "stubborn", "exec": f"{NODES}:Waiter", "params": {"ignore_stop": True, "pid_file": "{run_dir}/s.pid"}},
        {"name": "ticker", "exec": f"{NODES}:Ticker", "params": {"wait_for": "{run_dir}/s.pid"}},  # stubborn is up
    ], exit_when=["ticker"], stop_timeout_s=0.3)  # fmt: skip
    code, out = run_launch(load_launch(path))
    assert code == 0, out
    assert "stubborn: did not stop within 0.3 s; killed (SIGKILL)" in out
    pid = int((tmp_path / "run" / "s.pid").read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


@pytest.mark.parametrize("compose", [False, True])
def test_a_pub_sub_graph_runs_over_ipc_or_inproc(tmp_path, compose):
    path = write_launch(tmp_path, [
        {"name": "talker", "exec": f"{NODES}:Talker", "remap": {"chatter": "uav1/chatter"}},
        {"name": "listener", "exec": f"{NODES}:Listener", "params": {"topic_in": "uav1/chatter", "count": 3}},
    ], exit_when=["listener"], compose=compose)  # fmt: skip
    code, out = run_launch(load_launch(path))
    assert code == 0, out
    logs = read_logs(tmp_path)
    scheme = "inproc" if compose else "ipc"
    assert f"listening to uav1/chatter on {scheme}://{tmp_path.resolve()}/run/talk.sock" in logs["listener"]
    assert logs["listener"].count("heard uav1/chatter") == 3
    assert f"publishing uav1/chatter on {scheme}://" in logs["talker"]
