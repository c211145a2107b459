"""``olsplat service``: the unit it prints parses (``systemd-analyze verify`` where the machine
has it, else its INI structure), starts the installed ``olsplat``, and its ExecStartPre (the
launch's ``--check``) runs and passes on a valid replay launch."""

from __future__ import annotations

import shlex
import shutil
import subprocess

from olsplat_nodes.tools.service import device_unit, quote
from tests.helpers import free_port

from .conftest import OLSPLAT, run_olsplat


def _sections(text: str) -> dict[str, list[tuple[str, str]]]:
    """A unit file's sections -> (key, value) in order (keys repeat: After=, Environment=)."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    for line in text.splitlines():
        if not line.strip() or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], [])
            continue
        key, eq, value = line.partition("=")
        assert current is not None and eq and key.strip() == key and key, f"not a unit line: {line!r}"
        current.append((key, value))
    return sections


def _words(command: str) -> list[str]:
    """An Exec line's words as systemd passes them (quotes and escapes; %% and $$ stand for % and $)."""
    return [w.replace("%%", "%").replace("$$", "$") for w in shlex.split(command)]


def test_the_unit_parses_runs_olsplat_and_its_check_passes(tmp_path, replay_sets):
    port = free_port()
    args = ["--launch", "replay", "--run-dir", "run", *replay_sets,
            "--set", f"query_server.query_endpoint=tcp://127.0.0.1:{port}", "--set", "ingest.rate_hz=2"]  # fmt: skip
    done = run_olsplat("service", *args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    unit = tmp_path / "olsplat-replay.service"
    unit.write_text(done.stdout)
    sections = _sections(done.stdout)
    assert set(sections) == {"Unit", "Service", "Install"}
    service = dict(sections["Service"])
    if shutil.which("systemd-analyze"):
        verified = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
        assert verified.returncode == 0, verified.stderr
        broken = tmp_path / "broken.service"  # the verifier is live: it refuses a relative ExecStart
        broken.write_text(done.stdout.replace(f"ExecStart={OLSPLAT.resolve()}", "ExecStart=olsplat-nowhere/bin"))
        assert subprocess.run(["systemd-analyze", "verify", str(broken)], capture_output=True).returncode != 0
    start = _words(service["ExecStart"])
    assert start[0] == str(OLSPLAT.resolve()) and start[1:3] == ["launch", "replay"]
    assert start[3:5] == ["--run-dir", str(tmp_path / "run")] and start[5:] == args[4:]
    assert _words(service["ExecStartPre"]) == [start[0], "launch", "--check", *start[2:]]
    assert service["WorkingDirectory"] == str(tmp_path) and service["Restart"] == "on-failure"
    assert service["KillSignal"] == "SIGINT" and "130" in service["SuccessExitStatus"].split()
    assert int(service["TimeoutStopSec"]) > 5  # the replay launch's stop_timeout_s
    assert service["StandardOutput"] == "journal"
    assert dict(sections["Unit"])["Wants"] == "network-online.target"
    # ExecStartPre, run as systemd would: in WorkingDirectory, exit 0, nothing started
    pre = subprocess.run(_words(service["ExecStartPre"]), cwd=service["WorkingDirectory"], capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert pre.returncode == 0, pre.stdout + pre.stderr
    assert "0 blocker: ready" in pre.stdout and not (tmp_path / "run").exists()


def test_a_field_launch_waits_for_its_camera_and_serial_port(tmp_path):
    done = run_olsplat("service", "--launch", "field_drone", "--user", "uav", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    # no keys here yet: the unit is written, and a note says its check will refuse to start
    assert "note: the unit's ExecStartPre will refuse" in done.stderr and "keys/drone.key_secret" in done.stderr
    unit = dict(_sections(done.stdout)["Unit"])
    assert unit["After"].split() == ["network-online.target", "dev-oak.device", "dev-ttyACM0.device"]
    assert unit["Wants"] == unit["After"]
    assert 'ENV{SYSTEMD_ALIAS}="/dev/oak"' in done.stdout  # the udev rule that makes dev-oak.device
    service = dict(_sections(done.stdout)["Service"])
    assert service["User"] == "uav" and service["SupplementaryGroups"] == "dialout"


def test_a_bad_launch_prints_one_error_line_and_no_unit(tmp_path):
    done = run_olsplat("service", "--launch", "replay", "--set", "ingest.no_such_param=1", cwd=tmp_path)
    assert done.returncode == 1 and done.stdout == ""
    assert len(done.stderr.strip().splitlines()) == 1 and "no_such_param" in done.stderr


def test_systemd_names_and_quoting():
    assert device_unit("/dev/ttyACM0") == "dev-ttyACM0.device"
    assert (
        device_unit("/dev/serial/by-id/usb-ArduPilot_fmuv3-if00")
        == "dev-serial-by\\x2did-usb\\x2dArduPilot_fmuv3\\x2dif00.device"
    )
    assert quote("ingest.source=a b") == '"ingest.source=a b"'
    assert quote("rate=50%") == "rate=50%%"
    assert _words(quote('say "hi" $HOME 5%')) == ['say "hi" $HOME 5%']
