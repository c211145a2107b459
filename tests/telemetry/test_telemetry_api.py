"""The public names of olsplat_nodes.telemetry import, and the package ships with the distribution."""

import importlib
import tomllib
from pathlib import Path


def test_all_names_exist():
    mod = importlib.import_module("olsplat_nodes.telemetry")
    for name in mod.__all__:
        assert hasattr(mod, name), name


def test_package_and_pinned_dependency_are_declared():
    project = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    assert "olsplat_nodes.telemetry" in project["tool"]["setuptools"]["packages"]
    assert "pymavlink==2.4.50" in project["project"]["dependencies"]
    assert "pyserial==3.5" in project["project"]["dependencies"]
