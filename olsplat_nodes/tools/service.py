"""``olsplat service --launch NAME|FILE``: a systemd unit that runs exactly that launch on boot.

The unit it prints (install it as /etc/systemd/system/olsplat-NAME.service; docs/field-service.md):

- ``ExecStartPre=`` ``olsplat launch --check`` of the same launch and arguments: a blocker
  (a missing map, keys readable by others, a port taken, no camera) stops the start with the
  table in the journal, and ``Restart=on-failure`` tries again after ``RestartSec``, except
  after exit 65 (``RestartPreventExitStatus``: a node refused its input, a corrupt map or log,
  which a restart cannot mend; 78, a configuration such as a port taken, may pass on a retry);
- ``ExecStart=`` the installed ``olsplat`` executable (absolute path) with ``launch`` and the
  same arguments: the launch by its shipped name (it survives an upgrade) or the file's
  absolute path, ``--run-dir`` absolute, every ``--set``;
- ``WorkingDirectory=`` the folder the launch's relative paths (map, keys, logs) are taken from:
  ``--workdir``, by default the current directory (the one ``olsplat launch --check`` just
  checked them from; put the run folder in it, e.g. /var/lib/olsplat with --run-dir
  /var/lib/olsplat/run, and it is the run's parent);
- ``KillSignal=SIGINT`` to the supervisor only (``KillMode=mixed``): it stops its nodes in
  reverse start order as on Ctrl-C and exits 130 (``SuccessExitStatus=130 143``: a stop is not a
  failure); ``TimeoutStopSec`` the launch's ``stop_timeout_s`` plus 10 s, then SIGKILL to all;
- ``After=``/``Wants=network-online.target``; a serial MAVLink port (``telemetry_url``) adds
  ``After=``/``Wants=`` its device unit (``/dev/ttyACM0`` -> ``dev-ttyACM0.device``, tagged by
  systemd's own udev rules); a DepthAI camera adds ``dev-oak.device``, which needs the udev
  rule printed in the unit's comments (the OAK is a USB device systemd does not tag itself);
- output to the journal (``journalctl -u olsplat-NAME``), ``PYTHONUNBUFFERED=1``, and the
  ``NUMBA_CACHE_DIR`` / ``OLSPLAT_NATIVE`` of this shell when set (the cache ``olsplat doctor``
  found warm must be the flight's).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

from ..errors import EXIT_BAD_INPUT

EPILOG = """examples:
  cd /var/lib/olsplat && olsplat service --launch field_drone --run-dir run --user uav \\
      | sudo tee /etc/systemd/system/olsplat-field_drone.service
  sudo systemctl daemon-reload && sudo systemctl enable --now olsplat-field_drone
  journalctl -u olsplat-field_drone -f"""

OAK_UDEV_RULE = (
    'SUBSYSTEM=="usb", ENV{DEVTYPE}=="usb_device", ATTRS{idVendor}=="03e7", MODE="0666", '
    'TAG+="systemd", ENV{SYSTEMD_ALIAS}="/dev/oak"'
)
STOP_MARGIN_S = 10  # TimeoutStopSec beyond the launch's stop_timeout_s: the supervisor's own grace first
RESTART_SEC = 5


def add_parser(subparsers) -> None:
    from .launch_options import add_override_options

    parser = subparsers.add_parser(
        "service",
        help="print a systemd unit that runs a launch on boot (checked first, restarted on failure)",
        description=__doc__.split("\n\n", 1)[1],
        epilog=EPILOG,
    )
    parser.add_argument("--launch", required=True, metavar="NAME|FILE", help="a shipped launch name or a file")
    add_override_options(parser)
    parser.add_argument("--user", help="run as this user (User=); default: root")
    parser.add_argument("--workdir", help="WorkingDirectory=: where relative paths are taken from (default: here)")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import OlsplatInputError
    from ..launcher import find_launch_file, shipped_launch_files
    from ..launcher.preflight import plan_launch

    workdir = Path(args.workdir or os.getcwd()).absolute()
    # a bad launch (syntax, unknown params): one error line and no unit; values that only fail
    # here and now (keys not made yet) are the ExecStartPre's to refuse, said below
    plan = plan_launch(args.launch, args.overrides, args.run_dir, validate=False)
    path = find_launch_file(args.launch)
    shipped = shipped_launch_files()
    launch = path.stem if shipped.get(path.stem) == path.resolve() else str(path.absolute())
    run_dir = Path(args.run_dir) if args.run_dir else plan.config.run_dir
    run_dir = run_dir if run_dir.is_absolute() else (workdir / run_dir)
    print(
        unit_text(
            executable=olsplat_executable(),
            launch=launch,
            name=plan.config.name,
            run_dir=run_dir,
            overrides=args.overrides,
            workdir=workdir,
            stop_timeout_s=plan.config.stop_timeout_s,
            devices=device_units(plan),
            user=args.user,
            environment={k: os.environ[k] for k in ("NUMBA_CACHE_DIR", "OLSPLAT_NATIVE") if k in os.environ},
        ),
        end="",
    )
    try:
        plan_launch(args.launch, args.overrides, args.run_dir)
    except OlsplatInputError as exc:
        print(f"olsplat service: note: the unit's ExecStartPre will refuse to start until this is fixed: {exc}",
              file=sys.stderr)  # fmt: skip
    return 0


def olsplat_executable() -> str:
    """The absolute path of the ``olsplat`` executable running now (``sys.argv[0]``), else the
    one on PATH; else this Python with ``-m olsplat_nodes.cli``."""
    argv0 = Path(sys.argv[0])
    if argv0.name == "olsplat" and argv0.is_file():
        return str(argv0.resolve())
    found = shutil.which("olsplat")
    if found:
        return str(Path(found).resolve())
    return f"{Path(sys.executable).absolute()} -m olsplat_nodes.cli"


def device_units(plan) -> list[str]:
    """The device units the launch waits for: its serial MAVLink port, and the OAK camera (an
    alias the udev rule ``OAK_UDEV_RULE`` makes)."""
    units = []
    for name in plan.nodes_of("ingest"):
        params = plan.params[name]
        if params.get("source_kind") != "depthai":
            continue
        units.append("dev-oak.device")
        url = str(params.get("telemetry_url") or "")
        if url.startswith("/dev/"):
            units.append(device_unit(url))
    return list(dict.fromkeys(units))


def device_unit(path: str) -> str:
    """systemd's device unit of a /dev path (``systemd-escape --path --suffix=device``)."""
    parts = [p for p in path.split("/") if p]
    escaped = "-".join(re.sub(r"[^A-Za-z0-9:_.]", lambda m: "".join(f"\\x{b:02x}" for b in m[0].encode()), p)
                       for p in parts)  # fmt: skip
    if escaped.startswith("."):
        escaped = "\\x2e" + escaped[1:]
    return f"{escaped}.device"


def quote(arg: str) -> str:
    """One ``ExecStart=`` argument: systemd splits on spaces, reads C escapes in quotes, and
    expands ``%`` specifiers and ``$`` variables (doubled to stay literal)."""
    arg = arg.replace("%", "%%").replace("$", "$$")
    if arg and re.fullmatch(r"[A-Za-z0-9_./:=,+@%$-]+", arg):
        return arg
    return '"' + arg.replace("\\", "\\\\").replace('"', '\\"') + '"'


def command_line(executable: str, words: Sequence[str]) -> str:
    """``executable`` (which may carry ``-m module``) and the quoted ``words``."""
    return " ".join([*(quote(w) for w in executable.split(" ")), *(quote(w) for w in words)])


def unit_text(
    executable: str,
    launch: str,
    name: str,
    run_dir: Path,
    overrides: Sequence[str],
    workdir: Path,
    stop_timeout_s: float,
    devices: Sequence[str] = (),
    user: str | None = None,
    environment: dict[str, str] | None = None,
) -> str:
    """The unit file's text (see the module docstring)."""
    arguments = [launch, "--run-dir", str(run_dir)]
    for item in overrides:
        arguments += ["--set", item]
    after = ["network-online.target", *devices]
    lines = [
        f"# olsplat launch {launch}: made by `olsplat service`; install and use: docs/field-service.md",
        f"# sudo cp THIS /etc/systemd/system/olsplat-{name}.service && sudo systemctl daemon-reload",
        f"# sudo systemctl enable --now olsplat-{name}; journalctl -u olsplat-{name} -f",
    ]
    if "dev-oak.device" in devices:
        lines += [
            "# The OAK camera's device unit needs this udev rule (/etc/udev/rules.d/80-olsplat-oak.rules;",
            "# then sudo udevadm control --reload && sudo udevadm trigger):",
            f"#   {OAK_UDEV_RULE}",
        ]
    lines += [
        "",
        "[Unit]",
        f"Description=olsplat launch {name} (open-vocabulary mapping)",
        f"After={' '.join(after)}",
        f"Wants={' '.join(after)}",
        "StartLimitIntervalSec=300",
        "StartLimitBurst=10",
        "",
        "[Service]",
        "Type=exec",
    ]
    if user:
        lines.append(f"User={user}")
        if any(d.startswith("dev-tty") for d in devices):
            lines.append("SupplementaryGroups=dialout")
    lines += [
        f"WorkingDirectory={quote(str(workdir))}",
        "Environment=PYTHONUNBUFFERED=1",
        *(f"Environment={quote(f'{k}={v}')}" for k, v in sorted((environment or {}).items())),
        f"ExecStartPre={command_line(executable, ['launch', '--check', *arguments])}",
        f"ExecStart={command_line(executable, ['launch', *arguments])}",
        "Restart=on-failure",
        f"RestartSec={RESTART_SEC}",
        f"RestartPreventExitStatus={EXIT_BAD_INPUT}",
        "KillMode=mixed",
        "KillSignal=SIGINT",
        "SuccessExitStatus=130 143",
        f"TimeoutStopSec={math.ceil(stop_timeout_s) + STOP_MARGIN_S}",
        "StandardOutput=journal",
        "StandardError=journal",
        f"SyslogIdentifier=olsplat-{name}",
        "",
        "[Install]",
        "WantedBy=multi-user.target",
    ]
    return "\n".join(lines) + "\n"
