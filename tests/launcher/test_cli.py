"""``olsplat launch`` as a user runs it: a real launcher process, signals, exit codes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from olsplat_nodes.cli import main
from tests.helpers import wait_for

from .conftest import NODES, REPO, write_launch

OLSPLAT = Path(sys.executable).with_name("olsplat")


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_to_the_launcher_stops_every_child_and_sets_the_exit_code(tmp_path, sig, code):
    names = ["a", "b", "stubborn"]
    path = write_launch(tmp_path, [
        {"name": name, "exec": f"{NODES}:Waiter",
         "params": {"pid_file": "{run_dir}/{name}.pid", "ignore_stop": name == "stubborn"}} for name in names
    ], stop_timeout_s=0.5)  # fmt: skip
    run = tmp_path / "elsewhere"  # --run-dir replaces the file's run_dir
    launcher = subprocess.Popen([str(OLSPLAT), "launch", str(path), "--run-dir", str(run)], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        pid_files = [run / f"{name}.pid" for name in names]
        pids = wait_for(
            lambda: all(p.exists() for p in pid_files) and [int(p.read_text()) for p in pid_files], 10.0, "three nodes"
        )
        launcher.send_signal(sig)
        out, _ = launcher.communicate(timeout=15)
    finally:
        launcher.kill()
    assert launcher.returncode == code, out
    assert [pid for pid in pids if alive(pid)] == []
    assert f"stopping all nodes (received {sig.name})" in out
    assert "stubborn: did not stop within 0.5 s; killed (SIGKILL)" in out
    assert "a: stopped (exited with code 0)" in out and "b: stopped (exited with code 0)" in out
    assert (run / "logs" / "launch.log").read_text() == out


def test_launch_runs_a_file_to_its_end_with_overrides(tmp_path, capsys):
    path = write_launch(
        tmp_path, [{"name": "ticker", "exec": f"{NODES}:Ticker", "params": {"ticks": 50}}], exit_when=["ticker"]
    )
    assert main(["launch", str(path), "--set", "ticker.ticks=2", "--set", "ticker.note=from-cli"]) == 0
    assert "ticker: exited with code 0" in capsys.readouterr().out
    log = (tmp_path / "run" / "logs" / "ticker.log").read_text()
    assert "note=from-cli" in log and "ticker tick 1" in log and "ticker tick 2" not in log


def test_launch_errors_are_one_line_and_exit_1(tmp_path):
    path = write_launch(tmp_path, [{"name": "ticker", "exec": f"{NODES}:Ticker"}])
    command = [str(OLSPLAT), "launch", str(path), "--set", "tocker.ticks=2"]
    result = subprocess.run(command, capture_output=True, text=True, cwd=REPO, timeout=60)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [
        f"olsplat launch: error: {path}: --set 'tocker.ticks=2': no node named 'tocker'; "
        "nodes: ticker (or 'launch' for a top-level key)"
    ]
    assert not (tmp_path / "run").exists()  # nothing started, nothing written


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "accumulator.tau_dd=0.3",
            "nodes[3] (accumulator).params.tau_dd: unknown parameter of accumulator; did you mean tau_d or tau_e?",
        ),
        ("accumulator.tau_d=high", "nodes[3] (accumulator).params.tau_d: expected a number or null, got 'high'"),
        ("accumulator.tau_d=-1", "nodes[3] (accumulator).params: need kappa > 0, tau_d >= 0"),
        ("accumulator.method=outlangsplot", "nodes[3] (accumulator).params.method: unknown method 'outlangsplot'"),
        ("region_encoder.encoder_weights=0.6,0.4", "nodes[2] (region_encoder).params.encoder_weights: expected a list"),
        ("refiner.method=topk", "nodes[4] (refiner).params.method: unknown parameter of refiner; known: codebook"),
    ],
)
def test_the_shipped_graph_refuses_a_bad_parameter_at_launch_in_one_line(tmp_path, override, message):
    """A misspelt name, a wrong type or an out-of-range method value in the real replay graph
    is refused before any node starts: one line naming the file, the node and the parameter."""
    run = tmp_path / "run"
    result = subprocess.run(
        [str(OLSPLAT), "launch", "launch/replay.yaml", "--run-dir", str(run), "--set", override],
        capture_output=True, text=True, cwd=REPO, timeout=120,
    )  # fmt: skip
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("olsplat launch: error: launch/replay.yaml: "), lines
    assert message in lines[0]
    assert not run.exists()  # nothing started, nothing written


def test_a_run_folder_made_with_other_method_settings_is_refused_at_launch(tmp_path):
    from olsplat_nodes.method import MethodParams, StoreManifest, write_manifest

    run = tmp_path / "run"
    write_manifest(run / "store", StoreManifest(MethodParams(tau_d=0.3).resolve(), "shipped"))
    result = subprocess.run(
        [str(OLSPLAT), "launch", "launch/replay.yaml", "--run-dir", str(run), "--set", "accumulator.tau_d=0.2"],
        capture_output=True, text=True, cwd=REPO, timeout=120,
    )  # fmt: skip
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [
        f"olsplat launch: error: launch/replay.yaml: nodes[3] (accumulator).params: {run / 'store' / 'manifest.json'}: "
        "this store was made with other method settings (tau_d: 0.3 in the store, 0.2 now); "
        "use a new run folder or the store's own settings"
    ]
    assert sorted(p.name for p in run.iterdir()) == ["store"]  # nothing started


def test_shipped_launch_files_run_by_name_from_any_folder(tmp_path):
    """A pip-installed drone has no checkout: the five launch files ship in the package, are
    listed by ``--list`` and taken by name; an unknown name lists the shipped ones."""
    from olsplat_nodes.launcher import find_launch_file, load_launch, shipped_launch_files

    shipped = shipped_launch_files()
    assert set(shipped) == {"replay", "drone", "field_drone", "ground", "field_ground"}
    listed = subprocess.run(
        [str(OLSPLAT), "launch", "--list"], capture_output=True, text=True, cwd=tmp_path, timeout=60
    )
    assert listed.returncode == 0 and [line.split()[0] for line in listed.stdout.splitlines()[:5]] == sorted(shipped)
    assert find_launch_file("replay") == find_launch_file("replay.yaml") == shipped["replay"]
    assert load_launch("replay", run_dir=str(tmp_path / "run")).name == "replay"
    mine = tmp_path / "replay"  # a file of that name in the working folder wins over the shipped one
    mine.write_text("name: mine\nnodes: [{name: a, exec: ingest}]\n")
    assert find_launch_file(mine) == mine
    wrong = subprocess.run([str(OLSPLAT), "launch", "replya"], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert wrong.returncode == 1
    assert wrong.stderr.strip().splitlines() == [
        "olsplat launch: error: replya: no such launch file, nor a shipped launch file of that name "
        "(shipped: drone, field_drone, field_ground, ground, replay; olsplat launch --list)"
    ]
