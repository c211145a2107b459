"""The public names of each package import and are listed in __all__."""

import importlib
import subprocess
import sys

import pytest


@pytest.mark.parametrize(
    "module",
    [
        "olsplat_nodes",
        "olsplat_nodes.scene",
        "olsplat_nodes.raster",
        "olsplat_nodes.regions",
        "olsplat_nodes.encoders",
        "olsplat_msgs",
        "olsplat_sim",
    ],
)
def test_all_names_exist(module):
    mod = importlib.import_module(module)
    for name in mod.__all__:
        assert hasattr(mod, name), f"{module}.{name}"


def test_no_top_level_msgs_or_sim_module(tmp_path):
    """The folders msgs/ and sim/ install under olsplat_* names only (checked outside the repo)."""
    code = "import importlib.util as u; print([u.find_spec(n) is None for n in ('msgs', 'sim', 'olsplat_msgs')])"
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.stdout.strip() == "[True, True, False]", done.stderr
