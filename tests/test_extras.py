"""Optional extras: a feature whose extra is not installed is refused with one line naming it."""

from __future__ import annotations

import argparse

import pytest

from olsplat_nodes import cli
from olsplat_nodes.extras import EXTRA_OF_MODULE, MissingExtra, require


def test_require_names_the_extra_without_importing():
    require("numpy", "the base install")  # present: nothing happens
    with pytest.raises(MissingExtra, match=r"^the camera needs no_such_module_xyz, which is not installed: "
                                           r"pip install 'olsplat\[oak\]'$"):  # fmt: skip
        require("no_such_module_xyz", "the camera", "oak")


def test_every_extra_module_is_declared_in_pyproject():
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    for module, extra in EXTRA_OF_MODULE.items():
        assert any(req.split("=")[0].split(">")[0] == module for req in extras[extra]), (module, extra)
    base = {req.split("=")[0].split(">")[0] for req in project["dependencies"]}
    assert not base & set(EXTRA_OF_MODULE), base & set(EXTRA_OF_MODULE)


def test_a_command_that_reaches_a_missing_extra_prints_one_line(monkeypatch, capsys):
    """Whatever command imports a module of an extra that is missing: one line naming the
    extra and exit 1, not an "internal error" traceback; any other missing module stays a bug."""

    def needs_ray(args):
        raise ModuleNotFoundError("No module named 'ray'", name="ray")

    def needs_nothing_known(args):
        raise ModuleNotFoundError("No module named 'lost'", name="lost")

    for run, line in ((needs_ray, "pip install 'olsplat[cluster]'"), (needs_nothing_known, "internal error")):
        parser = argparse.ArgumentParser()
        parser.set_defaults(run=run, command="x")
        monkeypatch.setattr(cli, "build_parser", lambda parser=parser: parser)
        assert cli.main([]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert line in err[-1], err
        assert (len(err) == 1) == (run is needs_ray), err
