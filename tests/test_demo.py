"""``olsplat demo`` (what ``make demo`` runs) on the tiny preset, end to end: the flight made, the
five-node replay graph launched, the ground's queries answered while it streams and after the
final map, the pictures and the summary written, the graph stopped."""

from __future__ import annotations

import json

import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.tools.demo import DEMO_QUERIES

from .helpers import free_port

pytestmark = pytest.mark.timeout(420)


def test_the_demo_on_the_tiny_preset(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["demo", "--out", str(out), "--preset", "tiny", "--port", str(free_port()), "--timeout", "300"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["flight"] == {"preset": "tiny", "seed": 0, "frames": 12}
    assert summary["frames_aggregated"] == 12 and summary["map_version"] >= 1
    assert set(summary["drops"]) == {"ingest", "region_encoder", "accumulator", "refiner", "query_server"}
    assert all(v == 0 for v in summary["drops"].values()) and all(v == 0 for v in summary["bad_messages"].values())
    final = [q for q in summary["queries"] if q["phase"] == "final"]
    assert [q["text"] for q in final] == list(DEMO_QUERIES)
    assert all(q["status"] == "ok" and q["map_version"] == summary["map_version"] and q["view"] for q in final), final
    assert sum(q["instances_3d"] for q in final) >= 3  # roofs, road, trees and cars are in the tiny town
    pictures = sorted(p.name for p in (out / "ground").rglob("*.png"))
    assert len(pictures) >= 2 * len(DEMO_QUERIES), pictures  # a heatmap and a mask per query at least
    assert (out / "summary.md").read_text().startswith("# olsplat demo")
    assert "final map: version" in printed and f"ground web --run {out / 'run'}" in printed
    # a second demo reuses the flight and starts the graph over on a fresh store
    assert main(["demo", "--out", str(out), "--preset", "tiny", "--port", str(free_port()), "--timeout", "300"]) == 0
    assert "flight: reusing" in capsys.readouterr().out
    assert json.loads((out / "summary.json").read_text())["frames_aggregated"] == 12
