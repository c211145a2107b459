"""Checks of the flight computer itself: Python, cores, CPU features, the C kernels,
onnxruntime and the clock. Each function returns one ``Row``; none needs a launch file."""

from __future__ import annotations

import ctypes
import importlib.util
import os
import platform
import shutil
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

from ._row import Row, blocker, ok, warn

MIN_PYTHON = (3, 11)
# the C kernels' x86-64 build uses these (setup.py); numba's code is faster with them too
X86_FEATURES = frozenset(("avx2", "fma", "f16c"))
ARM_FEATURES = frozenset(("asimd",))  # NEON, as /proc/cpuinfo names it on aarch64
CLOCKSOURCE = Path("/sys/devices/system/clocksource/clocksource0/current_clocksource")
# clock sources that are read without a trap into the kernel: a timestamp costs tens of ns
FAST_CLOCKSOURCES = ("tsc", "arch_sys_counter", "kvm-clock", "hyperv_clocksource_tsc_page")
REINSTALL = "pip install --force-reinstall --no-deps olsplat (from the wheel or the checkout you installed)"


def python_version(version: tuple[int, ...] = tuple(sys.version_info[:3])) -> Row:
    """Python >= 3.11 (what olsplat is written for)."""
    text = ".".join(str(v) for v in version)
    if tuple(version[:2]) < MIN_PYTHON:
        return blocker("python", f"{text} at {sys.executable}", "install Python >= 3.11 and olsplat into it")
    return ok("python", f"{text} at {sys.executable}")


def cores() -> Row:
    """The cores this process may run on (its affinity mask, as the nodes' threads see it)."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    total = os.cpu_count() or usable
    figure = f"{usable} usable of {total}"
    if usable < 2:
        return warn("cores", figure, "the five nodes need 2 cores to keep up with 1 frame/s; lower ingest rate_hz")
    return ok("cores", figure)


def cpu_flags(cpuinfo: str | None = None) -> set[str]:
    """The CPU's feature flags from /proc/cpuinfo (x86 "flags", ARM "Features"); empty if unreadable."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            return set(value.split())
    return set()


def cpu_features(machine: str = platform.machine(), cpuinfo: str | None = None) -> Row:
    """The vector instructions the kernels use: x86-64 AVX2, FMA, F16C; aarch64 NEON (asimd)."""
    flags = cpu_flags(cpuinfo)
    if machine in ("x86_64", "AMD64"):
        wanted, fix = X86_FEATURES, "a CPU without AVX2 runs the portable kernels (about twice the time): expect it"
    elif machine in ("aarch64", "arm64"):
        wanted, fix = ARM_FEATURES, "a CPU without NEON runs scalar code: expect slower frames"
    else:
        return warn("cpu features", f"{machine}: not a tested architecture", "olsplat is tested on x86-64 and aarch64")
    if not flags:
        return warn("cpu features", f"{machine}: /proc/cpuinfo unreadable", "run on Linux, or check the CPU by hand")
    missing = sorted(wanted - flags)
    if missing:
        return warn("cpu features", f"{machine}: missing {', '.join(missing)}", fix)
    return ok("cpu features", f"{machine}: {' '.join(sorted(wanted))}")


def native_kernels(env: Mapping[str, str] = os.environ) -> Row:
    """The C kernels (``olsplat_nodes.native``): loaded, or why not: disabled by OLSPLAT_NATIVE=0,
    the extension missing (no C compiler at install), not loadable, or built for AVX2 on a CPU
    without it. Without them the numba kernels serve: the same results, about twice the time."""
    name = "C kernels"
    if env.get("OLSPLAT_NATIVE", "1") == "0":
        return warn(
            name,
            "disabled: OLSPLAT_NATIVE=0 (numba kernels serve, about twice the time)",
            "unset OLSPLAT_NATIVE (or set it to 1)",
        )
    spec = importlib.util.find_spec("olsplat_nodes.native._kernels")
    if spec is None or spec.origin is None:
        return warn(
            name,
            "missing: olsplat_nodes.native._kernels was not built (numba kernels serve, 2x the time)",
            f"install a C compiler (apt-get install gcc), then {REINSTALL}",
        )
    try:
        loaded = ctypes.CDLL(spec.origin)
        avx2 = bool(loaded.built_with_avx2())
    except (OSError, AttributeError) as exc:
        return warn(name, f"{spec.origin}: cannot be loaded ({exc})", REINSTALL)
    if avx2 and not X86_FEATURES <= frozenset(cpu_flags()):
        return warn(
            name,
            "built for AVX2 on a CPU without avx2/fma/f16c: numba kernels serve (2x the time)",
            f"rebuild on this machine: {REINSTALL}",
        )
    from ...native import library

    if library() is None:  # the loader's own verdict, in case its rules grew
        return warn(name, f"{Path(spec.origin).name}: olsplat_nodes.native.library() declines it", REINSTALL)
    return ok(name, f"loaded {Path(spec.origin).name} ({'AVX2' if avx2 else 'portable'} build)")


def onnxruntime_providers() -> Row:
    """onnxruntime importable, with the CPU provider the encoders run on."""
    try:
        import onnxruntime
    except ImportError as exc:
        return blocker("onnxruntime", f"not importable ({exc})", "pip install onnxruntime (an olsplat dependency)")
    providers = onnxruntime.get_available_providers()
    figure = f"{onnxruntime.__version__}: {', '.join(providers)}"
    if "CPUExecutionProvider" not in providers:
        return blocker("onnxruntime", figure, "install the CPU build: pip install --force-reinstall onnxruntime")
    return ok("onnxruntime", figure)


def clock_source(path: Path = CLOCKSOURCE) -> Row:
    """The kernel's clock source: every frame, message and heartbeat is stamped with it."""
    try:
        source = path.read_text().strip()
    except OSError:
        return warn("clock source", f"unknown ({path} unreadable)", "not Linux, or /sys not mounted: check by hand")
    if source not in FAST_CLOCKSOURCES:
        return warn(
            "clock source",
            f"{source}: each timestamp is a slow hardware read",
            f"use tsc (x86) or arch_sys_counter (ARM) if offered: cat {path.parent}/available_clocksource",
        )
    return ok("clock source", source)


def clock_sync(timeout_s: float = 3.0) -> Row:
    """Whether the system clock is synchronised (NTP, chrony, GPS): frames carry wall-clock
    stamps and the ground station compares them. ``timedatectl`` where systemd runs, else the
    kernel's own estimate (adjtimex: maximum error below 16 s, systemd's rule), else unknown."""
    name = "clock sync"
    timedatectl = shutil.which("timedatectl")
    if timedatectl is not None:
        try:
            out = subprocess.run(
                [timedatectl, "show", "-p", "NTPSynchronized", "--value"],
                capture_output=True,
                text=True,
                timeout=timeout_s,
            )
        except (OSError, subprocess.TimeoutExpired):
            out = None
        if out is not None and out.returncode == 0 and out.stdout.strip() in ("yes", "no"):
            if out.stdout.strip() == "yes":
                return ok(name, "synchronised (timedatectl NTPSynchronized=yes)")
            return warn(
                name,
                "not synchronised (timedatectl NTPSynchronized=no)",
                "timedatectl set-ntp true, or a GPS/chrony time source; wait until it is synchronised",
            )
    maxerror_us = _adjtimex_maxerror_us()
    if maxerror_us is None:
        return warn(name, "unknown (no timedatectl, adjtimex unavailable)", "check the time source (chronyc tracking)")
    if maxerror_us < 16_000_000:
        return ok(name, f"synchronised (kernel max error {maxerror_us / 1000:.0f} ms)")
    return warn(
        name,
        "not synchronised (the kernel's max error is 16 s or more)",
        "start an NTP client (chrony, systemd-timesyncd) or a GPS time source",
    )


class _Timex(ctypes.Structure):
    # the head of Linux's struct timex (LP64: x86-64 and aarch64); the kernel writes the rest
    _fields_ = [("modes", ctypes.c_uint), ("offset", ctypes.c_long), ("freq", ctypes.c_long),
                ("maxerror", ctypes.c_long), ("esterror", ctypes.c_long), ("status", ctypes.c_int),
                ("rest", ctypes.c_char * 256)]  # fmt: skip


def _adjtimex_maxerror_us() -> int | None:
    """The kernel clock's maximum error in µs (adjtimex with modes 0 only reads), or None."""
    if sys.platform != "linux":
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        timex = _Timex()
        if libc.adjtimex(ctypes.byref(timex)) < 0:
            return None
    except (OSError, AttributeError):
        return None
    return int(timex.maxerror)
