"""The ground page's "since flight" selector over an aggregate's per-flight maps, through
``RunReview`` and a real ``GroundPage`` (its viser server; no browser): the session's three
flights of the tiny town (training seed 1005; f0 = A, f1 = B after the default changes, f2 = N
without them, "now": since f1 the changes are undone), the views of N saved as a run's views. The
page's change answer is ``olsplat query --since``'s."""

from __future__ import annotations

import json

import numpy as np
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.ground.review import RunReview
from tests.query.test_change_flights import TINY_CUTS

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def run(change_flights):
    from olsplat_nodes.pipeline import Scene
    from olsplat_nodes.storage import save_view

    scene = Scene.open(change_flights / "N")
    for index, camera in enumerate(scene.cameras[:3]):
        save_view(change_flights / "out" / "views", index, camera, scene.image(camera))
    return change_flights


def test_since_flight_gives_the_change_of_olsplat_query_since(run, tmp_path):
    ply = run / "N" / "map" / "point_cloud.ply"
    review = RunReview(run / "out", ply, max_splats=5000, heatmap_cache_mb=0, change_cuts=TINY_CUTS)
    try:
        assert review.flights() == ["f0", "f1"]
        view = review.cameras()[2].name
        answer = review.ask("", [], view, since="f1")
        assert (
            answer.status == "ok" and answer.since == "f1" and "what changed since flight f1 (now f2)" in answer.message
        )
        args = ["query", "--map", str(run / "out" / "flights" / "f2"), "--since", str(run / "out" / "flights" / "f1")]
        assert (
            main([*args, "--scene", str(run / "N"), "--json", str(tmp_path / "q.json"), "--change-cuts", TINY_CUTS])
            == 0
        )
        expected = json.loads((tmp_path / "q.json").read_text())["instances"]
        assert len(expected) >= 1
        assert [list(i.centre) for i in answer.instances] == [i["centre"] for i in expected]
        assert answer.margin is not None and answer.margin.shape == (len(review.splats.ids),)
        assert np.nanmax(answer.margin) > 0 > np.nanmin(answer.margin)  # changed splats above the cut, others below
        assert answer.heatmap_picture is not None and answer.mask_picture is not None
        assert answer.heatmap_picture.dtype == np.uint8 and answer.heatmap_picture.shape[2] == 3
        # an ordinary query over this folder (no map/): no map, as before
        assert review.ask("cars", []).status == "no_map"
        assert review.ask("", [], since="f2").status == "bad_request"
    finally:
        review.close()


# the page's theme call (viser's own deprecation, not this feature's)
@pytest.mark.filterwarnings("ignore:`control_layout` is deprecated:DeprecationWarning")
def test_the_page_shows_the_selector_and_asks_the_change(run):
    from olsplat_nodes.ground.page import GroundPage

    review = RunReview(run / "out", run / "N" / "map" / "point_cloud.ply", 5000, 0, change_cuts=TINY_CUTS)
    page = GroundPage(review, port=0)
    try:
        assert page.since_choice.visible and tuple(page.since_choice.options) == ("none", "f0", "f1")
        page.since_choice.value = "f1"
        page._ask("", [])
        assert page.answer is not None and page.answer.since == "f1" and page.answer.instances
        assert "what changed since flight f1" in page.query_message.content
    finally:
        page.server.stop()
        review.close()
