"""The architecture docs/architecture.md ("Package layout") promises, checked on the source: every import, also the
lazy ones inside functions, followed transitively.

- No node imports another node: nodes share code through ``nodes/base.py`` (the loop) and
  ``nodes/convert.py`` (messages <-> core values) only.
- Nothing on the drone's runtime path imports the simulator: a drone install runs the core,
  the nodes, the sources, the transport, the launcher and the telemetry without ``olsplat_sim``.
  Only the command-line tools, the benchmarks and the offline evaluation may.
- The core never touches a socket: no zmq below the nodes and the transport.
- Ray is an optional extra: only ``olsplat_nodes.cluster`` imports it, and only the command-line
  tools and the benchmarks import that package.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"olsplat_nodes": ROOT / "olsplat_nodes", "olsplat_msgs": ROOT / "msgs", "olsplat_sim": ROOT / "sim"}
NODE_MODULES = {"ingest", "region_encoder", "accumulator", "refiner", "query_server", "ground_monitor"}
# May import the simulator: user-facing tools and studies, not the drone's runtime.
OFFLINE = ("olsplat_nodes.tools", "olsplat_nodes.bench", "olsplat_nodes.evaluate", "olsplat_nodes.pipeline")
OFFLINE_MODULES = ("olsplat_nodes.cli",)
SOCKET_LAYERS = ("olsplat_nodes.nodes", "olsplat_nodes.transport", "olsplat_nodes.launcher", "olsplat_nodes.tools")


def _modules() -> dict[str, Path]:
    out = {}
    for package, folder in PACKAGES.items():
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join((package, *parts))] = path
    return out


MODULES = _modules()


def _imports(name: str) -> set[str]:
    """Every module ``name`` imports (absolute names; relative imports resolved), at any depth
    of its code."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found |= {f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in MODULES}
    return found


def _closure(name: str) -> dict[str, str]:
    """Every module reachable from ``name`` -> the module that imports it (for the error path)."""
    seen, todo = {name: ""}, [name]
    while todo:
        current = todo.pop()
        for imported in _imports(current):
            target = imported
            while target and target not in MODULES:  # "olsplat_sim.x.y" where y is a name
                target = target.rpartition(".")[0]
            if target.split(".")[0] not in PACKAGES:
                seen.setdefault(imported, current)
                continue
            if target and target not in seen:
                seen[target] = current
                todo.append(target)
    return seen


def _path(seen: dict[str, str], end: str) -> str:
    chain = [end]
    while seen.get(chain[-1]):
        chain.append(seen[chain[-1]])
    return " <- ".join(chain)


def _runtime_modules() -> list[str]:
    return [
        m
        for m in MODULES
        if m.startswith(("olsplat_nodes", "olsplat_msgs")) and not m.startswith(OFFLINE) and m not in OFFLINE_MODULES
    ]


def test_the_walk_sees_lazy_and_relative_imports():
    # the accumulator imports the store inside a function, relatively: the walk must see both
    assert "olsplat_nodes.aggregate" in _imports("olsplat_nodes.nodes.accumulator")
    assert "olsplat_sim" in {m.split(".")[0] for m in _closure("olsplat_nodes.cli")}


def test_no_node_imports_another_node():
    for node in NODE_MODULES:
        name = f"olsplat_nodes.nodes.{node}"
        seen = _closure(name)
        others = {f"olsplat_nodes.nodes.{n}" for n in NODE_MODULES - {node}}
        bad = sorted(others & set(seen))
        assert not bad, f"{name} imports another node: {_path(seen, bad[0])}"


def test_the_runtime_path_does_not_import_the_simulator():
    runtime = _runtime_modules()
    assert "olsplat_nodes.sources.replay" in runtime and "olsplat_nodes.method" in runtime
    for name in runtime:
        seen = _closure(name)
        bad = sorted(m for m in seen if m.split(".")[0] == "olsplat_sim")
        assert not bad, f"{name} reaches the simulator: {_path(seen, bad[0])}"


def test_the_core_never_touches_a_socket():
    for name in _runtime_modules():
        if name.startswith(SOCKET_LAYERS) or name.startswith("olsplat_msgs"):
            continue
        seen = _closure(name)
        bad = sorted(m for m in seen if m.split(".")[0] == "zmq")
        assert not bad, f"{name} reaches zmq: {_path(seen, bad[0])}"


def test_the_nodes_start_without_torch():
    """torch takes a second or more to import, and five nodes start at once on two cores:
    only the 3D branch with a MinkUNet checkpoint (and the offline tools) may import it."""
    import subprocess
    import sys

    modules = [f"olsplat_nodes.nodes.{n}" for n in sorted(NODE_MODULES)]
    modules += ["olsplat_nodes.method", "olsplat_nodes.aggregate", "olsplat_nodes.raster", "olsplat_nodes.regions"]
    modules += ["olsplat_nodes.encoders.spec", "olsplat_nodes.query.answer", "olsplat_nodes.sources"]
    code = f"import importlib, sys\nfor m in {modules!r}: importlib.import_module(m)\nprint('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False", result.stdout + result.stderr


def test_only_the_cluster_package_imports_ray():
    for name in MODULES:
        if name.startswith("olsplat_nodes.cluster"):
            continue
        direct = {m.split(".")[0] for m in _imports(name)}
        assert "ray" not in direct, f"{name} imports ray: only olsplat_nodes.cluster may (an optional extra)"
        cluster = sorted(m for m in _imports(name) if m.startswith("olsplat_nodes.cluster"))
        assert not cluster or name.startswith(("olsplat_nodes.tools", "olsplat_nodes.bench")), f"{name}: {cluster[0]}"
