"""The layers docs/architecture.md ("Layers") promises, checked on the source: every import, also
the lazy ones inside functions, resolved to the module it loads.

One rule: ``LAYERS`` lists every package bottom-up, and a package imports only itself and the
packages listed before it (lower layers, or earlier in its own layer). No import cycle between
modules anywhere. Beside it, what the layers alone do not say:

- No node imports another node: nodes share code through ``nodes/base.py`` (the loop) and
  ``transport/convert.py`` (messages <-> core values) only.
- The core never touches a socket: zmq only from the transport layer up.
- Nothing on the drone's runtime path imports the simulator (it sits in the top layer).
- Ray is an optional extra: only ``olsplat_nodes.cluster`` imports it, and only the command-line
  tools and the benchmarks import that package.
- The nodes start without torch.
"""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"olsplat_nodes": ROOT / "olsplat_nodes", "olsplat_msgs": ROOT / "msgs", "olsplat_sim": ROOT / "sim"}

# Bottom-up. Names are olsplat_nodes' subpackages and top-level modules, and the two sibling
# packages olsplat_msgs and olsplat_sim. Keep docs/architecture.md's table in step with this one.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("base", ("olsplat_nodes", "errors", "params", "durable", "outputs", "memory", "extras")),
    ("wire", ("olsplat_msgs",)),
    ("core numerics", ("scene", "native", "raster", "regions", "encoders", "structure", "aggregate", "viz")),
    ("storage", ("storage",)),
    ("method", ("method", "query", "pipeline")),
    ("graph transport", ("transport",)),
    ("drone runtime", ("telemetry", "sources", "nodes", "launcher")),
    ("ground station", ("ground",)),
    ("offline", ("cluster", "evaluate", "olsplat_sim", "tools", "bench", "cli")),
]
ORDER = [package for _, packages in LAYERS for package in packages]
NODE_MODULES = {"ingest", "region_encoder", "accumulator", "refiner", "query_server", "ground_monitor"}


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
    of its code. ``from . import sub`` names the submodule only: the package is already loaded
    when one of its own modules runs."""
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
            submodules = {f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in MODULES}
            own_package = node.level and not node.module and name.startswith(base + ".")
            if not (own_package and len(submodules) == len(node.names)):
                found.add(base)
            found |= submodules
    return found


def _module_of(imported: str) -> str:
    """The module of ours an import loads ("olsplat_sim.x.y" where y is a name -> olsplat_sim.x),
    or "" for another distribution's."""
    target = imported
    while target and target not in MODULES:
        target = target.rpartition(".")[0]
    return target


def _package(module: str) -> str:
    """The entry of ``ORDER`` a module belongs to."""
    parts = module.split(".")
    return parts[1] if parts[0] == "olsplat_nodes" and len(parts) > 1 else parts[0]


def _closure(name: str) -> dict[str, str]:
    """Every module reachable from ``name`` -> the module that imports it (for the error path)."""
    seen, todo = {name: ""}, [name]
    while todo:
        current = todo.pop()
        for imported in _imports(current):
            target = _module_of(imported)
            if not target:
                seen.setdefault(imported, current)
            elif target not in seen:
                seen[target] = current
                todo.append(target)
    return seen


def _path(seen: dict[str, str], end: str) -> str:
    chain = [end]
    while seen.get(chain[-1]):
        chain.append(seen[chain[-1]])
    return " <- ".join(chain)


def _cycles() -> list[list[str]]:
    """The modules of an import cycle, sorted ([] when there is none; one cycle at a time:
    the standard library's topological sort stops at the first it meets)."""
    graph = {m: {_module_of(i) for i in _imports(m)} - {"", m} for m in MODULES}
    try:
        graphlib.TopologicalSorter(graph).prepare()
    except graphlib.CycleError as exc:
        return [sorted(set(exc.args[1]))]
    return []


def test_the_walk_sees_lazy_and_relative_imports():
    # the accumulator imports the store inside a function, relatively: the walk must see both
    assert "olsplat_nodes.storage" in _imports("olsplat_nodes.nodes.accumulator")
    assert "olsplat_sim" in {m.split(".")[0] for m in _closure("olsplat_nodes.cli")}


def test_every_package_has_a_layer():
    assert len(ORDER) == len(set(ORDER)), "a package is listed twice"
    packages = {_package(m) for m in MODULES}
    assert packages <= set(ORDER), f"not in LAYERS (give each a layer): {sorted(packages - set(ORDER))}"
    assert set(ORDER) <= packages, f"in LAYERS but not in the source: {sorted(set(ORDER) - packages)}"


def test_every_import_goes_down_the_layers():
    wrong = []
    for name in sorted(MODULES):
        rank = ORDER.index(_package(name))
        for imported in sorted(_imports(name)):
            target = _module_of(imported)
            if target and ORDER.index(_package(target)) > rank:
                wrong.append(f"{name} imports {target} ({_package(name)} is below {_package(target)})")
    assert not wrong, "imports that go up the layers:\n" + "\n".join(wrong)


def test_no_import_cycle():
    cycles = _cycles()
    assert not cycles, "modules that import each other:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle(monkeypatch):
    """The cycle test can fail: two modules importing each other are reported."""
    fake = {"olsplat_nodes.a": {"olsplat_nodes.b"}, "olsplat_nodes.b": {"olsplat_nodes.a"}}
    monkeypatch.setattr(f"{__name__}.MODULES", dict.fromkeys(fake, Path("x")))
    monkeypatch.setattr(f"{__name__}._imports", lambda name: fake[name])
    assert _cycles() == [["olsplat_nodes.a", "olsplat_nodes.b"]]


def test_no_node_imports_another_node():
    for node in NODE_MODULES:
        name = f"olsplat_nodes.nodes.{node}"
        seen = _closure(name)
        others = {f"olsplat_nodes.nodes.{n}" for n in NODE_MODULES - {node}}
        bad = sorted(others & set(seen))
        assert not bad, f"{name} imports another node: {_path(seen, bad[0])}"


def test_the_runtime_path_does_not_import_the_simulator():
    runtime = [m for m in MODULES if ORDER.index(_package(m)) <= ORDER.index("ground")]
    assert "olsplat_nodes.sources.replay" in runtime and "olsplat_nodes.method" in runtime
    for name in runtime:
        seen = _closure(name)
        bad = sorted(m for m in seen if m.split(".")[0] == "olsplat_sim")
        assert not bad, f"{name} reaches the simulator: {_path(seen, bad[0])}"


def test_the_core_never_touches_a_socket():
    below_transport = [m for m in MODULES if ORDER.index(_package(m)) < ORDER.index("transport")]
    for name in below_transport:
        seen = _closure(name)
        bad = sorted(m for m in seen if m.split(".")[0] == "zmq")
        assert not bad, f"{name} reaches zmq: {_path(seen, bad[0])}"


def test_the_nodes_start_without_torch():
    """torch takes a second or more to import, and five nodes start at once on two cores:
    only the 3D branch with a MinkUNet checkpoint (and the offline tools) may import it."""
    import subprocess
    import sys

    modules = [f"olsplat_nodes.nodes.{n}" for n in sorted(NODE_MODULES)]
    modules += ["olsplat_nodes.method", "olsplat_nodes.aggregate", "olsplat_nodes.storage", "olsplat_nodes.raster"]
    modules += ["olsplat_nodes.regions", "olsplat_nodes.encoders.spec", "olsplat_nodes.query.answer"]
    modules += ["olsplat_nodes.sources", "olsplat_nodes.method.live"]
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
