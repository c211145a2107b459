"""What a launch takes from the machine: disk space for the flight, the TCP ports it binds, the
length of its ipc:// socket paths. Each function returns one ``Row`` (or one per port); the
port test binds a plain socket and closes it at once (no ZeroMQ here).
"""

from __future__ import annotations

import errno
import math
import os
import socket
from pathlib import Path

from ...durable import DiskRunway, free_mb
from ._launch import LaunchPlan
from ._row import Row, blocker, ok, warn

DEFAULT_RATE_HZ = 1.0  # views per second when the launch does not say (a replay at its recorded pace)
# views per second a latest-wins graph stores at most on two cores (docs/benchmarks.md: 1.28 on
# the small preset at 640x480, fewer on larger maps and images); frames beyond it are dropped
MAX_STORED_RATE_HZ = 1.3
DEFAULT_PIXELS = 1280 * 960  # the image size when the launch does not say (as the memory estimate)
IPC_PATH_MAX = 107  # bytes: sockaddr_un.sun_path (108) less its terminating NUL


# --- disk -----------------------------------------------------------------------------------


def estimated_bytes_per_view(gaussians: int, pixels: int) -> float:
    """Disk bytes one stored view takes, from the prior map's Gaussians and the image's pixels,
    before any view was stored: the store segment grows with the pixels and, as the map gets
    denser, with the Gaussians each pixel sees: measured 3.5, 7.8, 9.3 and 14.3 bytes per pixel
    on the tiny, small, medium and large presets (26 k, 0.39 M, 1.3 M, 5.2 M Gaussians;
    docs/benchmarks.md "store per view"), which 0.22 N^0.27 fits within 10 %; 0.25 N^0.27 here,
    to err high. The photo (JPEG quality 95) adds at most 1.5 bytes per pixel. ``gaussians`` 0
    (unknown) counts as 5 M."""
    n = gaussians if gaussians > 0 else 5_000_000
    return (0.25 * n**0.27 + 1.5) * pixels


def measured_bytes(store: Path, views: Path) -> tuple[int, int]:
    """(bytes, views) a run has stored so far: its store segments (``store/views/NNNNNN/``) and
    photos (``views/``), as the accumulator counts them (``DiskRunway``); (0, 0) for no run."""
    segments = [p for p in (store / "views").glob("*") if p.is_dir() and not p.name.endswith(".tmp")]
    if not segments:
        return 0, 0
    written = sum(f.stat().st_size for seg in segments for f in seg.iterdir() if f.is_file())
    if views.is_dir():
        written += sum(f.stat().st_size for f in views.iterdir() if f.is_file())
    return written, len(segments)


def frame_rate(plan: LaunchPlan) -> tuple[float, str]:
    """Views per second the launch will store, and where that figure comes from: its ingest's
    frame rate, at most ``MAX_STORED_RATE_HZ`` when frames are latest-wins (the rest are
    dropped, not stored); ``DEFAULT_RATE_HZ`` when the launch does not say."""
    for name in plan.nodes_of("ingest"):
        p = plan.params[name]
        if p.get("source_kind") == "depthai":
            rate, source = float(p["depthai_fps"]), f"{name}.depthai_fps"
        elif float(p.get("rate_hz") or 0) > 0 and not p.get("fast"):
            rate, source = float(p["rate_hz"]), f"{name}.rate_hz"
        else:
            continue
        if not p.get("lossless") and rate > MAX_STORED_RATE_HZ:
            return MAX_STORED_RATE_HZ, f"{source}={rate:g}, latest-wins: at most {MAX_STORED_RATE_HZ:g} stored"
        return rate, source
    return DEFAULT_RATE_HZ, "default"


def disk(plan: LaunchPlan, minutes: float, rate_hz: float | None = None) -> Row | None:
    """Free space on the disk of the accumulator's store for ``minutes`` of flight at
    ``rate_hz`` views per second (default: the launch's frame rate, else 1/s; a latest-wins
    graph stores fewer frames than the camera gives, so this errs high). Bytes per view:
    measured from the run's store when there is one (``DiskRunway``, its 20 % margin), else
    ``estimated_bytes_per_view`` from the map and image size. None for a launch that stores
    no views (no accumulator)."""
    from ...scene.ply import ply_header

    nodes = plan.nodes_of("accumulator")
    if not nodes:
        return None
    p = plan.params[nodes[0]]
    store, photos = Path(p["store"]), Path(p["views"])
    rate, source = (rate_hz, "--rate") if rate_hz is not None else frame_rate(plan)
    views = math.ceil(minutes * 60.0 * rate)
    written, stored = measured_bytes(store, photos)
    if stored:
        runway = DiskRunway(written, stored)
        how = f"measured on {stored} views of {store}"
    else:
        header = ply_header(p["map"]) if p.get("map") else None
        ingest = [plan.params[n] for n in plan.nodes_of("ingest") if plan.params[n].get("source_kind") == "depthai"]
        pixels = int(ingest[0]["depthai_width"]) * int(ingest[0]["depthai_height"]) if ingest else DEFAULT_PIXELS
        runway = DiskRunway(int(estimated_bytes_per_view(header[0] if header else 0, pixels)), 1)
        count = f"{header[0]:,}" if header else "an unknown number of"
        how = f"estimated for {count} Gaussians at {pixels / 1e6:.1f} Mpx"
    folder = _existing(store)
    free = free_mb(folder) * 2**20
    need = runway.need(views)
    per_view = (runway.bytes_per_view or 0.0) / 2**20
    figure = (
        f"{free / 2**30:,.1f} GB free on {folder}; {minutes:g} min at {rate:g} views/s ({source}) x "
        f"{per_view:.2f} MB/view ({how}) +20 % = {need / 2**30:,.1f} GB"
    )
    if not math.isfinite(free):
        return warn("disk", f"free space of {folder} unreadable", "check the disk by hand (df -h)")
    if need > free:
        room_min = free / max(runway.need(1) * rate * 60.0, 1.0)
        return blocker("disk", figure, f"room for ~{room_min:.0f} min: free space, a bigger disk, or a shorter flight")
    if need > 0.5 * free:
        return warn("disk", figure, "less than twice the room needed: free space before a long flight")
    return ok("disk", figure)


def _existing(path: Path) -> Path:
    """``path`` or its nearest existing parent (a run folder is made at launch)."""
    path = path.resolve()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


# --- ports and sockets ----------------------------------------------------------------------


def bound_endpoints(plan: LaunchPlan) -> list[tuple[str, str]]:
    """(``node.param``, endpoint) of every endpoint a node binds: params named ``*_out``,
    ``*_bind`` and ``query_endpoint`` (the nodes' publishers, the diagnostics collector and
    the query server's router); the ``*_in`` ones and ``connect`` connect."""
    found = []
    for name, params in plan.params.items():
        for key, value in params.items():
            if isinstance(value, str) and value and (key.endswith(("_out", "_bind")) or key == "query_endpoint"):
                found.append((f"{name}.{key}", value))
    return found


def port_rows(plan: LaunchPlan) -> list[Row]:
    """One row per TCP port the launch binds: free now, or a blocker naming what holds it."""
    return [tcp_port(endpoint, param) for param, endpoint in bound_endpoints(plan) if endpoint.startswith("tcp://")]


def tcp_port(endpoint: str, param: str) -> Row:
    """Whether ``tcp://HOST:PORT`` can be bound now (a plain socket with SO_REUSEADDR, as
    ZeroMQ binds: a port left in TIME_WAIT is free, one with a listener is not)."""
    host, _, port_text = endpoint[len("tcp://") :].rpartition(":")
    host = host.strip("[]")
    name = f"port {port_text}"
    if port_text in ("*", "!", "0"):
        return ok(f"port {endpoint}", f"{param}: any free port")
    if not port_text.isdigit() or not 0 < int(port_text) < 65536:
        return blocker(name, f"{endpoint}: not tcp://HOST:PORT ({param})", f"--set {param}=tcp://127.0.0.1:5600")
    port = int(port_text)
    address = "0.0.0.0" if host in ("*", "") else host
    family = socket.AF_INET6 if ":" in address else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((address, port))
    except socket.gaierror:
        return warn(
            name,
            f"{endpoint}: host {host!r} is not an address (a ZeroMQ interface name?); not tested",
            f"bind an address: --set {param}=tcp://0.0.0.0:{port}",
        )
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            holder = port_holder(port)
            return blocker(
                name,
                f"{endpoint} is in use{' by ' + holder if holder else ''} ({param})",
                f"stop {holder or 'what holds it'}, or --set {param}=tcp://{host}:OTHER_PORT",
            )
        if exc.errno == errno.EADDRNOTAVAIL:
            return blocker(
                name,
                f"{endpoint}: {host} is not an address of this machine ({param})",
                f"--set {param}=tcp://0.0.0.0:{port} (every interface) or this machine's address",
            )
        if exc.errno == errno.EACCES:
            return blocker(
                name, f"{endpoint}: ports below 1024 need root ({param})", f"--set {param}=tcp://{host}:5600"
            )
        return blocker(name, f"{endpoint}: cannot bind ({exc.strerror}) ({param})", f"--set {param}=...")
    return ok(name, f"{endpoint} free ({param})")


def port_holder(port: int, proc: Path = Path("/proc")) -> str | None:
    """``pid 1234 (python3)`` of the process listening on TCP ``port``, from /proc/net/tcp{,6}
    and the processes' socket descriptors; ``another user's process`` when its descriptors
    cannot be read; None when /proc does not tell."""
    inodes = set()
    for table in ("tcp", "tcp6"):
        try:
            lines = (proc / "net" / table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 9 and fields[3] == "0A" and int(fields[1].rpartition(":")[2], 16) == port:
                inodes.add(f"socket:[{fields[9]}]")
    if not inodes:
        return None
    hidden = False
    for pid_dir in proc.iterdir():
        if not pid_dir.name.isdigit():
            continue
        try:
            fds = list((pid_dir / "fd").iterdir())
        except OSError:
            hidden = True
            continue
        for fd in fds:
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target in inodes:
                try:
                    comm = (pid_dir / "comm").read_text().strip()
                except OSError:
                    comm = "?"
                return f"pid {pid_dir.name} ({comm})"
    return "another user's process" if hidden else None


def ipc_paths(plan: LaunchPlan) -> Row | None:
    """The ipc:// socket paths fit in a Unix socket address (107 bytes): a long run folder
    makes ZeroMQ refuse to bind. None when the launch has none (composed: inproc)."""
    paths = sorted(
        {
            v[len("ipc://") :]
            for params in plan.params.values()
            for v in params.values()
            if isinstance(v, str) and v.startswith("ipc://")
        }
    )
    if not paths:
        return None
    longest = max(paths, key=lambda p: len(p.encode()))
    figure = f"{len(paths)} sockets, longest {len(longest.encode())} of {IPC_PATH_MAX} bytes ({longest})"
    if len(longest.encode()) > IPC_PATH_MAX:
        return blocker("ipc sockets", figure, "a shorter run folder: --run-dir /var/lib/olsplat/run, say")
    return ok("ipc sockets", figure)
