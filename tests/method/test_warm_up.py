"""The nodes' warm-ups compile what a real frame needs: in a fresh process (so that no other
test has compiled anything), after the warm-up a full-size frame adds no numba signature.
A warm-up that used other array types, or skipped a kernel because nothing was in its view,
would leave that compilation (seconds on a fresh install) to the flight's first frame."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

COMPILED = """
import json, sys
import numba.core.registry

def compiled():
    out = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("olsplat_nodes"):
            for attr, value in list(vars(module).items()):
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    out[name + "." + attr] = len(value.signatures)
    return out
"""


def _run(body: str) -> dict:
    script = COMPILED + textwrap.dedent(body)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("method", ["outlangsplat", "vala"])
def test_the_accumulator_warm_up_compiles_what_a_frame_needs(method):
    result = _run(
        f"""
        from olsplat_nodes.method import MethodParams, view_observations, warm_up
        from tests.conftest import camera_for, random_gaussians
        from tests.method.test_view_step import _regions

        method = MethodParams(method="{method}").resolve()
        gaussians = random_gaussians(3000, 3, seed=4)
        warm_up(gaussians, method)
        before = compiled()
        camera = camera_for("PINHOLE_CENTRED", 160, 120)
        label_maps, bank = _regions(camera.height, camera.width, dim=64)
        observations, _, _ = view_observations(gaussians, camera, label_maps, bank, method)
        print(json.dumps({{"before": before, "after": compiled(), "kept": len(observations)}}))
        """
    )
    assert result["kept"] > 100  # the frame saw the map
    assert sum(result["before"].values()) >= 3  # projection, binning, observations at least
    assert result["after"] == result["before"]


def test_the_region_encoder_warm_up_compiles_what_a_frame_needs():
    result = _run(
        """
        import numpy as np
        from olsplat_nodes.encoders.spec import encoder_from_spec
        from olsplat_nodes.nodes.region_encoder import warm_up
        from olsplat_nodes.encoders import encode_regions
        from olsplat_nodes.regions import RegionConfig, propose_regions

        encoder = encoder_from_spec(threads=1)
        config = RegionConfig(level_counts=(240,), work_scale=0.5)
        warm_up(encoder, config)
        before = compiled()
        rng = np.random.default_rng(1)
        image = np.kron(rng.integers(0, 256, (30, 40, 3)), np.ones((16, 16, 1))).astype(np.uint8)  # 480x640 blocks
        bank = encode_regions(image, propose_regions(image, config), encoder)
        print(json.dumps({"before": before, "after": compiled(), "regions": len(bank.features[0])}))
        """
    )
    assert result["regions"] > 50
    assert sum(result["before"].values()) >= 2
    assert result["after"] == result["before"]


def test_the_refiner_warm_up_compiles_what_a_pass_needs(tmp_path):
    result = _run(
        f"""
        from olsplat_nodes.method import add_view, named_method
        from olsplat_nodes.method.live import LiveMap, warm_up
        from olsplat_nodes.storage import LanguageMap, ObservationStore, write_snapshot
        from tests.conftest import camera_for, random_gaussians
        from tests.method.test_view_step import _regions

        warm_up()
        before = compiled()
        method = named_method("outlangsplat")
        gaussians = random_gaussians(3000, 3, seed=4)
        store = ObservationStore("{tmp_path}/store", len(gaussians), writer=True)
        live = LiveMap(store)
        camera = camera_for("PINHOLE_CENTRED", 160, 120)
        for view in range(3):  # a first exact pass, a fold, the final exact pass
            add_view(gaussians, camera, *_regions(camera.height, camera.width, dim=64), method, store)
            live.update(method.aggregation, exact=view != 1)
        write_snapshot(__import__("pathlib").Path("{tmp_path}/map"), 1,
                       LanguageMap(live.features, live.observed, "e"), {{}}, None)
        after = {{k: v for k, v in compiled().items() if k.startswith(("olsplat_nodes.aggregate.refine",
                                                                       "olsplat_nodes.storage"))}}
        print(json.dumps({{"before": before, "after": after, "observed": int(live.observed.sum())}}))
        """
    )
    assert result["observed"] > 100
    assert result["before"].get("olsplat_nodes.aggregate.refine._consistency") == 1
    assert len(result["after"]) >= 3 and all(result["before"].get(k) == n for k, n in result["after"].items()), result


def test_olsplat_warm_up_runs_every_node_stage(tmp_path):
    from olsplat_nodes.tools.warm_up import warm_up_all

    stages = warm_up_all(tmp_path)
    assert list(stages) == [
        "tiny flight made",
        "regions and features",
        "per-view step + refiner, outlangsplat",
        "per-view step + refiner, vala",
        "query, relevance and heatmap",
    ]
    assert all(seconds >= 0 for seconds in stages.values())
