"""Checks of one launch: the file and every node's params, the memory it needs, the files it
reads, the optional extras its settings need, the camera, the autopilot's port and the CURVE
keys. Each function returns one ``Row`` (or one per file); none starts a node or opens a socket.

Relative paths are taken from the current directory, as the nodes will (they inherit the
launcher's). The extras a node's settings need (``EXTRAS``): ingest ``source_kind: depthai`` ->
``[oak]`` (depthai); accumulator ``features: 2d3d`` -> ``[structure]`` (torch, open3d). No node
setting needs viser (``[ground]``: ``olsplat ground web``) or ray (``[cluster]``: ``olsplat
aggregate --cluster``): those are the ground station's and the offline tools'.
"""

from __future__ import annotations

import importlib.util
import os
import re
import stat
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...errors import OlsplatInputError
from .._config import LaunchConfig, load_launch
from ._row import Row, blocker, ok, warn


@dataclass(frozen=True)
class LaunchPlan:
    """A launch file as it would run: its config and every node's effective params (its class's
    defaults, then the file's and ``--set``'s values, placeholders substituted)."""

    config: LaunchConfig
    params: dict[str, dict[str, Any]]  # node name -> every param the node will run with

    def nodes_of(self, exec_name: str) -> list[str]:
        """Names of the nodes running ``exec_name`` (``"ingest"``)."""
        return [node.name for node in self.config.nodes if node.exec == exec_name]


def plan_launch(
    name_or_file: str, overrides: Sequence[str] = (), run_dir: str | None = None, validate: bool = True
) -> LaunchPlan:
    """Load, override and resolve a launch (``load_launch`` + ``resolve_launch``); raises the
    ``LaunchFileError`` naming file and key that ``olsplat launch`` would. ``validate=False``
    skips the node classes' own checks of their values (files such as keys may not exist yet
    where a unit file is written); unknown params and placeholders are still errors."""
    from ...nodes.base import node_class
    from .._resolve import resolve_launch, resolve_params

    config = load_launch(name_or_file, overrides=overrides, run_dir=run_dir)
    absolute = config.run_dir.resolve()
    if validate:
        resolved = resolve_launch(config, absolute)
    else:
        resolved = {
            node.name: resolve_params(node, node_class(node.exec).defaults(), absolute, config.namespace_of(node),
                                      config.compose, where=f"{config.source}: nodes[{i}] ({node.name})")
            for i, node in enumerate(config.nodes)
        }  # fmt: skip
    params = {node.name: {**node_class(node.exec).defaults(), **resolved[node.name]} for node in config.nodes}
    return LaunchPlan(config, params)


def launch_file(name_or_file: str, overrides: Sequence[str] = (), run_dir: str | None = None
                ) -> tuple[Row, LaunchPlan | None]:  # fmt: skip
    """The launch file valid, with every node's params checked by its class (names, types,
    ranges, cross-field rules): the row, and the plan when it is."""
    try:
        plan = plan_launch(name_or_file, overrides, run_dir)
    except OlsplatInputError as exc:
        return blocker("launch file", " ".join(str(exc).split()), "correct the file or the --set named above"), None
    config = plan.config
    figure = f"{config.source}: {len(config.nodes)} nodes ({', '.join(n.name for n in config.nodes)}), params valid"
    return ok("launch file", figure), plan


def memory(plan: LaunchPlan) -> Row:
    """The launch's memory estimate against its budget (the supervisor's own check)."""
    from .._memory import available_mb, check_memory

    try:
        estimates = check_memory(plan.config, plan.params)
    except OlsplatInputError as exc:
        return blocker("memory", " ".join(str(exc).split()), "a smaller map, or a computer with more memory")
    need = sum(e.mb for e in estimates)
    budget = plan.config.memory_budget_mb or available_mb()
    return ok(
        "memory",
        f"~{need:,.0f} MB estimated of {budget:,.0f} MB "
        f"({'memory_budget_mb' if plan.config.memory_budget_mb else 'available now'})",
    )


# --- input files ----------------------------------------------------------------------------


def input_rows(plan: LaunchPlan) -> list[Row]:
    """One row per file or folder the launch reads: the prior map (once, naming every node
    that reads it), the ingest's replay log, image folder or photo folder, and exported
    encoders. A missing one is a blocker naming it and the params that give it."""
    wanted: dict[tuple[str, str], list[str]] = {}  # (kind, path) -> ["node.param", ...]
    for name, params in plan.params.items():
        exec_name = plan.config.node(name).exec
        if exec_name in ("accumulator", "refiner", "query_server"):
            wanted.setdefault(("map", params.get("map", "")), []).append(f"{name}.map")
        elif exec_name == "ingest" and params.get("source_kind") in ("replay", "exif_folder"):
            wanted.setdefault((params["source_kind"], params.get("source", "")), []).append(f"{name}.source")
        elif exec_name == "region_encoder":
            from ...encoders.shipped import REGISTERED

            for part in str(params.get("encoder", "")).split(","):
                if part and part != "shipped" and part not in REGISTERED:
                    wanted.setdefault(("encoder", part), []).append(f"{name}.encoder")
    return [_input(kind, path, given) for (kind, path), given in wanted.items()]


def _input(kind: str, path: str, given: list[str]) -> Row:
    name = f"input {kind}"
    where = ", ".join(given)
    if not path:
        return blocker(name, f"not set ({where})", f"--set {given[0]}=PATH")
    target = Path(path)
    check = _CHECKS[kind]
    problem, figure = check(target)
    if problem:
        also = f" (and {', '.join(given[1:])} alike)" if len(given) > 1 else ""
        return blocker(name, f"{path}: {problem} ({where})", f"give an existing one: --set {given[0]}=PATH{also}")
    return ok(name, f"{path}: {figure} ({where})")


def _map(path: Path) -> tuple[str, str]:
    from ...scene.ply import ply_header

    if not path.is_file():
        return "no such file", ""
    header = ply_header(path)
    if header is None:
        return "not a PLY file with a vertex element", ""
    return "", f"{header[0]:,} Gaussians"


def _replay(path: Path) -> tuple[str, str]:
    from ...sources.rosbag import is_rosbag2

    if is_rosbag2(path) or path.name == "metadata.yaml":
        return _bag(path)
    if path.is_file():
        if not os.access(path, os.R_OK):
            return "not readable", ""
        return "", f"replay log, {path.stat().st_size / 2**20:.1f} MB"
    if path.is_dir():
        model = next((d for d in (path / "sparse" / "0", path) if any(d.glob("cameras.*"))), None)
        if model is None:
            return "a folder without a COLMAP model (sparse/0/cameras.bin or .txt)", ""
        images = path / "images" if (path / "images").is_dir() else path
        return "", f"image folder, {sum(1 for _ in images.iterdir())} files, COLMAP model in {model}"
    return "no such file or folder", ""


def _bag(path: Path) -> tuple[str, str]:
    """A ROS 2 bag opens and has images (which topics the ingest's ``bag_*`` params pick, and
    whether each frame has a pose, ``olsplat bag info BAG --check`` says in full)."""
    from ...errors import SceneFormatError
    from ...sources.rosbag_info import bag_summary

    try:
        summary = bag_summary(path, tf_messages=0)
    except SceneFormatError as exc:
        return exc.problem, ""
    images = [t for t in summary.topics if t.role == "image"]
    if not images:
        return "a ROS 2 bag without an Image or CompressedImage topic", ""
    counts = ", ".join(f"{t.topic} {t.count}" for t in images)
    return "", f"ROS 2 bag ({summary.storage}), {summary.duration_ns / 1e9:.0f} s, images: {counts}"


def _exif_folder(path: Path) -> tuple[str, str]:
    if not path.is_dir():
        return "no such folder", ""
    photos = [p for p in path.iterdir() if p.suffix.lower() in (".jpg", ".jpeg")]
    if not photos:
        return "holds no .jpg photos", ""
    return "", f"{len(photos)} photos"


def _encoder(path: Path) -> tuple[str, str]:
    if not (path / "encoder.json").is_file():
        return "not an exported encoder folder (no encoder.json; olsplat export-clip makes one)", ""
    return "", "exported encoder"


_CHECKS: dict[str, Callable[[Path], tuple[str, str]]] = {
    "map": _map,
    "replay": _replay,
    "exif_folder": _exif_folder,
    "encoder": _encoder,
}


# --- optional extras ------------------------------------------------------------------------

# (exec, param, value) -> (extra, modules it provides)
EXTRAS: dict[tuple[str, str, Any], tuple[str, tuple[str, ...]]] = {
    ("ingest", "source_kind", "depthai"): ("oak", ("depthai",)),
    ("accumulator", "features", "2d3d"): ("structure", ("torch", "open3d")),
}


def extra_rows(plan: LaunchPlan) -> list[Row]:
    """One row per optional extra a node's settings need: its modules importable, or a blocker
    with the pip command (found without importing them: torch alone takes seconds)."""
    rows = []
    for (exec_name, param, value), (extra, modules) in EXTRAS.items():
        users = [f"{n}.{param}={value}" for n in plan.nodes_of(exec_name) if plan.params[n].get(param) == value]
        if not users:
            continue
        missing = [m for m in modules if importlib.util.find_spec(m) is None]
        name = f"extra [{extra}]"
        if missing:
            rows.append(
                blocker(
                    name,
                    f"{', '.join(missing)} not installed, needed by {', '.join(users)}",
                    f"pip install 'olsplat[{extra}]'",
                )
            )
        else:
            rows.append(ok(name, f"{', '.join(modules)} installed ({', '.join(users)})"))
    return rows


# --- field hardware -------------------------------------------------------------------------


def camera_rows(plan: LaunchPlan, discover: Callable[[str], list] | None = None) -> list[Row]:
    """For each ingest with ``source_kind: depthai``: depthai importable and the camera listed
    by ``depthai.Device.getAllAvailableDevices`` (``depthai_device`` when it names one)."""
    rows = []
    for name in plan.nodes_of("ingest"):
        params = plan.params[name]
        if params.get("source_kind") != "depthai":
            continue
        want = params.get("depthai_device", "")
        if discover is None:
            if importlib.util.find_spec("depthai") is None:
                rows.append(
                    blocker(
                        "camera", f"depthai not installed ({name}.source_kind=depthai)", "pip install 'olsplat[oak]'"
                    )
                )
                continue
            from ...sources.oak import discover_devices

            discover = discover_devices
        try:
            devices = discover(want)
        except Exception as exc:  # a broken USB stack or driver: report it, do not crash the table
            rows.append(blocker("camera", f"DepthAI device listing failed: {exc}", "check the USB connection"))
            continue
        if not devices:
            which = f"device {want!r}" if want else "device"
            rows.append(
                blocker(
                    "camera",
                    f"no DepthAI {which} found ({name})",
                    f"plug in the OAK camera (USB3 port), install Luxonis' udev rule, or set {name}.depthai_device",
                )
            )
            continue
        ids = ", ".join(f"{d.getDeviceId()} ({getattr(d.state, 'name', d.state)})" for d in devices)
        rows.append(ok("camera", f"{len(devices)} DepthAI device(s): {ids}"))
    return rows


# pyserial URL schemes (serial.serial_for_url's urlhandler modules)
_PYSERIAL_SCHEMES = ("loop", "socket", "rfc2217", "spy", "hwgrep", "alt", "cp2110")


def mavlink_rows(plan: LaunchPlan) -> list[Row]:
    """For each ingest with ``telemetry_url``: a serial device that exists and this user can
    read and write, or a pyserial URL that parses (``socket://HOST:PORT``, ...). The reader
    opens it with ``serial.serial_for_url``, which has no UDP handler."""
    rows = []
    for name in plan.nodes_of("ingest"):
        params = plan.params[name]
        url = str(params.get("telemetry_url") or "")
        if not url or params.get("source_kind") != "depthai":
            continue
        rows.append(mavlink_port(url, int(params.get("telemetry_baudrate", 57600)), f"{name}.telemetry_url"))
    return rows


def mavlink_port(url: str, baudrate: int, param: str) -> Row:
    """One MAVLink link: ``url`` a device path or a pyserial URL."""
    name = "mavlink port"
    scheme, sep, rest = url.partition("://")
    if sep:
        if scheme not in _PYSERIAL_SCHEMES:
            return blocker(
                name,
                f"{url}: pyserial has no {scheme}:// handler ({param})",
                "a serial device (/dev/ttyACM0) or socket://HOST:PORT (a TCP bridge such as mavlink-router)",
            )
        if scheme in ("socket", "rfc2217"):
            match = re.fullmatch(r"(\[[^\]]+\]|[^:/?]+):(\d+)(\?.*)?", rest)
            if not match or not 0 < int(match.group(2)) < 65536:
                return blocker(
                    name, f"{url}: expected {scheme}://HOST:PORT ({param})", f"--set {param}={scheme}://HOST:PORT"
                )
        return ok(name, f"{url} ({scheme}:// via pyserial; the link itself is tried at launch)")
    device = Path(url)
    if not device.exists():
        return blocker(
            name,
            f"{url}: no such device ({param})",
            f"connect the autopilot's telemetry port, or --set {param}=/dev/ttyUSB0 (ls /dev/serial/by-id)",
        )
    mode = device.stat().st_mode
    if not stat.S_ISCHR(mode):
        return blocker(name, f"{url}: not a character device ({param})", f"--set {param}=THE_SERIAL_DEVICE")
    if not os.access(device, os.R_OK | os.W_OK):
        return blocker(
            name,
            f"{url}: this user cannot read and write it",
            "sudo usermod -aG dialout $USER (then log in again), or run the service as a dialout member",
        )
    return ok(name, f"{url}: serial device, read/write, {baudrate} baud")


# --- CURVE keys -----------------------------------------------------------------------------

_SECRET_LINE = re.compile(r'^\s*secret-key\s*=\s*"(.{40})"\s*$', re.MULTILINE)
_PUBLIC_LINE = re.compile(r'^\s*public-key\s*=\s*"(.{40})"\s*$', re.MULTILINE)


def key_rows(plan: LaunchPlan) -> list[Row]:
    """The CURVE key files the launch names: secret files present, holding a secret key, and
    private (mode 0600: a blocker otherwise, as the nodes refuse them); public files and the
    allow-list folder present (an empty allow-list lets no client in: a warning)."""
    rows = []
    for name, params in plan.params.items():
        exec_name = plan.config.node(name).exec
        if exec_name == "query_server" and params.get("server_secret"):
            rows.append(secret_key(Path(params["server_secret"]), f"{name}.server_secret"))
            rows.append(allow_list(Path(params.get("allow_dir") or ""), f"{name}.allow_dir"))
        elif exec_name == "ground_monitor" and params.get("client_secret"):
            rows.append(secret_key(Path(params["client_secret"]), f"{name}.client_secret"))
            rows.append(public_key(Path(params.get("server_public") or ""), f"{name}.server_public"))
    return rows


def secret_key(path: Path, param: str) -> Row:
    name = f"key {param}"
    if not path.is_file():
        return blocker(
            name,
            f"{path}: no such file",
            f"olsplat keys generate --out {path.parent} --name {path.name.removesuffix('.key_secret')}",
        )
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        return blocker(
            name, f"{path}: cannot be read ({exc.strerror})", f"make it readable by this user: chown $USER {path}"
        )
    if not _SECRET_LINE.search(text):
        return blocker(
            name,
            f"{path}: holds no secret key (a NAME.key public file?)",
            f"give the NAME.key_secret file: --set {param}=...",
        )
    mode = path.stat().st_mode & 0o777
    if mode & 0o077:
        return blocker(name, f"{path}: mode {mode:04o}, readable by others", f"chmod 600 {path}")
    return ok(name, f"{path}: secret key, mode {mode:04o}")


def public_key(path: Path, param: str) -> Row:
    name = f"key {param}"
    if not path.is_file():
        return blocker(
            name, f"{path or '(not set)'}: no such file", f"copy the server's NAME.key here, or --set {param}=..."
        )
    if not _PUBLIC_LINE.search(path.read_text(encoding="utf-8", errors="replace")):
        return blocker(name, f"{path}: holds no public key", f"give the server's NAME.key file: --set {param}=...")
    return ok(name, f"{path}: public key")


def allow_list(folder: Path, param: str) -> Row:
    name = f"key {param}"
    if not folder.is_dir():
        return blocker(
            name,
            f"{folder or '(not set)'}: no such folder",
            f"mkdir -p {folder} and copy each ground station's NAME.key into it",
        )
    keys = sorted(p.name for p in folder.glob("*.key"))
    if not keys:
        return warn(
            name, f"{folder}: no *.key file, no client can connect", f"copy the ground station's NAME.key into {folder}"
        )
    return ok(name, f"{folder}: {len(keys)} client key(s) ({', '.join(keys[:3])}{', ...' if len(keys) > 3 else ''})")
