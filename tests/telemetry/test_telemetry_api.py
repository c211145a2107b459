"""The public names of olsplat_nodes.telemetry import, and the package ships with the distribution."""

import importlib
import tomllib
from pathlib import Path


def test_all_names_exist():
    mod = importlib.import_module("olsplat_nodes.telemetry")
    for name in mod.__all__:
        assert hasattr(mod, name), name


def test_package_and_pinned_dependency_are_declared():
    """The package is found as setup.py finds packages (tests/test_wheel.py checks the wheel has
    every module), and its dependencies are in the base install, pinned."""
    from setuptools import find_namespace_packages

    root = Path(__file__).resolve().parents[2]
    project = tomllib.loads((root / "pyproject.toml").read_text())
    found = find_namespace_packages(where=str(root), include=["olsplat_nodes", "olsplat_nodes.*"])
    assert "olsplat_nodes.telemetry" in found
    assert "pymavlink==2.4.50" in project["project"]["dependencies"]
    assert "pyserial==3.5" in project["project"]["dependencies"]
