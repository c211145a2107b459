"""The optional extras of the install, by role, and the one-line refusal when one is missing.

The base install (``pip install olsplat``) is the flight computer's: the 2D branch, the five
nodes, the field sources, the simulator. What only some roles need comes as an extra
(``pip install 'olsplat[oak]'``); the table below maps each optional top-level module to the
extra that installs it. A launch that needs a missing extra is refused before any node starts
(the nodes' ``validate``), and a command that reaches one anyway prints the same one line
(``cli.main`` catches the ``ModuleNotFoundError``).
"""

from __future__ import annotations

import importlib.util

from .errors import OlsplatInputError

# optional top-level module -> the extra that installs it (pyproject.toml's optional-dependencies)
EXTRA_OF_MODULE: dict[str, str] = {
    "torch": "structure",
    "open3d": "structure",
    "depthai": "oak",
    "viser": "ground",
    "ray": "cluster",
    "onnx": "export",
    "onnxscript": "export",
    "pyproj": "geo",
}


class MissingExtra(OlsplatInputError):
    """Something the user asked for needs an optional extra that is not installed."""


def missing_extra_message(module: str, what: str, extra: str | None = None) -> str:
    """``"<what> needs <module> (not installed): pip install 'olsplat[<extra>]'"``."""
    extra = extra or EXTRA_OF_MODULE.get(module.split(".")[0], "all")
    return f"{what} needs {module}, which is not installed: pip install 'olsplat[{extra}]'"


def require(module: str, what: str, extra: str | None = None) -> None:
    """Raise ``MissingExtra`` naming the extra when ``module`` cannot be imported here.

    Only looks the module up (``importlib.util.find_spec``): nothing is imported, so a check at
    launch costs nothing even for torch. ``extra`` defaults to ``EXTRA_OF_MODULE``'s entry."""
    if importlib.util.find_spec(module) is None:
        raise MissingExtra(missing_extra_message(module, what, extra))
