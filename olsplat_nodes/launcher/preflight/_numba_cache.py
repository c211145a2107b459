"""Is numba's cache warm for this machine? (``olsplat warm-up`` fills it.)

numba compiles a kernel on its first call; with ``cache=True`` it keeps the machine code in an
index file (``MODULE.FUNC-LINE.pyXY.nbi``) and data files (``.nbc``) found by the kernel's
cache locator: ``NUMBA_CACHE_DIR`` when set, else ``__pycache__`` beside the source, else the
user's cache folder. The index is keyed per compiled signature by (signature, the target's
"magic tuple": LLVM triple, CPU name and CPU features, hashes of the kernel's bytecode and
closure), and is only valid for the source file's current modification time and size and
numba's version (numba/core/caching.py). So a kernel has usable machine code here when its
index, read through numba's own ``FunctionCache`` of the dispatcher, holds an entry whose key
numba would compute for this CPU and this bytecode, and that entry's data file exists: what
numba's ``load_overload`` looks up before it compiles. A cache copied from another CPU, left
by an older install, or an empty ``NUMBA_CACHE_DIR`` has none.

The kernels checked: every ``cache=True`` dispatcher in the modules of the runtime packages
(not the offline tools) whose source says ``cache=True``, except ``inline="always"`` helpers
(compiled into their callers, never on their own). A few run only with some settings and
``olsplat warm-up`` does not compile them (``CONDITIONAL``): cold, they are a warning when the
setting is on (``settings``) and a note otherwise. Nothing is compiled here.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from pathlib import Path

from ._row import Row, blocker, ok, warn

_ROOT = Path(__file__).resolve().parents[2]  # olsplat_nodes/
# packages whose kernels no node runs (command-line studies); the nodes' kernels are elsewhere
_OFFLINE = ("tools", "bench", "evaluate", "cluster", "pipeline")


# kernel -> the setting that runs it (a tag of ``numba_cache(settings=...)``) and what it does
CONDITIONAL = {
    "winners._winning_rows_float32": ("no-native", "queries without the C kernels"),
    "winners.gather_verdicts": ("codebook", "queries on a codebook map (refiner codebook > 0)"),
}


@dataclass(frozen=True)
class KernelCache:
    """One cached kernel: ``name`` (module.function), whether machine code for this CPU is in
    its cache, and the folder numba keeps it in."""

    name: str
    warm: bool
    folder: str


def kernel_modules() -> list[str]:
    """The runtime modules that define ``cache=True`` kernels (found by their source text)."""
    names = []
    for path in sorted(_ROOT.rglob("*.py")):
        parts = path.relative_to(_ROOT).with_suffix("").parts
        if parts[0] in _OFFLINE or "launcher" in parts:
            continue
        if "cache=True" in path.read_text(encoding="utf-8"):
            names.append(".".join(("olsplat_nodes", *(parts[:-1] if parts[-1] == "__init__" else parts))))
    return names


def kernel_caches(modules: list[str] | None = None) -> list[KernelCache]:
    """Every ``cache=True`` kernel of ``modules`` (default ``kernel_modules()``) and whether its
    machine code for this CPU is in numba's cache (see the module docstring)."""
    from numba.core.caching import FunctionCache
    from numba.core.dispatcher import Dispatcher
    from numba.core.registry import cpu_target

    codegen = cpu_target.target_context.codegen()
    found = []
    for module_name in modules if modules is not None else kernel_modules():
        module = importlib.import_module(module_name)
        for attr, value in sorted(vars(module).items()):
            if not isinstance(value, Dispatcher) or value.__module__ != module_name:
                continue  # imported from elsewhere: checked in its own module
            cache = getattr(value, "_cache", None)
            if not isinstance(cache, FunctionCache) or value.targetoptions.get("inline") == "always":
                continue  # cache=False, or compiled into its callers only
            index = cache._cache_file._load_index()  # {} when absent, stale or of another numba
            warm = any(
                key == cache._index_key(key[0], codegen) and os.path.exists(cache._cache_file._data_path(data))
                for key, data in index.items()
            )
            found.append(KernelCache(f"{module_name.rpartition('.')[2]}.{attr}", warm, cache.cache_path))
    return found


def numba_cache(modules: list[str] | None = None, settings: frozenset[str] = frozenset()) -> Row:
    """The row: every node kernel has machine code for this CPU in numba's cache, or a blocker
    (a cold cache cost half a flight's frames: the first minute is spent compiling). ``settings``:
    the ``CONDITIONAL`` tags that are on ("no-native", "codebook")."""
    name = "numba cache"
    fix = "olsplat warm-up (once after an install, ~75 s; with the NUMBA_CACHE_DIR the flight will have)"
    try:
        kernels = kernel_caches(modules)
    except Exception as exc:  # a numba whose private cache layout moved: say so, do not crash the table
        return warn(name, f"cannot be inspected ({type(exc).__name__}: {exc})", "run olsplat warm-up to be sure")
    if not kernels:
        return warn(name, "no cached kernels found to check", "run olsplat warm-up to be sure")
    cold = [k.name for k in kernels if not k.warm and k.name not in CONDITIONAL]
    needed = [k.name for k in kernels if not k.warm and CONDITIONAL.get(k.name, ("",))[0] in settings]
    later = [k.name for k in kernels if not k.warm and k.name in CONDITIONAL and k.name not in needed]
    folders = sorted({k.folder for k in kernels})
    where = os.environ.get("NUMBA_CACHE_DIR") or (folders[0] if len(folders) == 1 else "__pycache__ beside the sources")
    required = len(kernels) - len([k for k in kernels if k.name in CONDITIONAL])
    if cold:
        return blocker(
            name,
            f"cold: {len(cold)} of {required} node kernels not compiled for this CPU ({_some(cold)}); cache: {where}",
            fix,
        )
    figure = f"warm: {required} node kernels compiled for this CPU; cache: {where}"
    if needed:
        uses = sorted({CONDITIONAL[k][1] for k in needed})
        return warn(
            name,
            f"{figure}; not compiled: {_some(needed)} ({'; '.join(uses)}): a first such query compiles",
            "expect the first such query to take seconds longer",
        )
    if later:
        figure += f"; {len(later)} for other settings compile at first use"
    return ok(name, figure)


def _some(names: list[str], shown: int = 3) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")
