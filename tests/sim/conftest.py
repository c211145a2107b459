"""The tiny preset, generated once per test session (it takes a few seconds)."""

from __future__ import annotations

import pytest

from olsplat_sim.make import make_dataset
from olsplat_sim.presets import PRESETS


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny") / "scene"
    summary = make_dataset(PRESETS["tiny"], 0, out, log=lambda *_: None)
    return out, summary
