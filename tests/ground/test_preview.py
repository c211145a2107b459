"""The page's preview: a query over a view asks the view's small pictures first
(``RunReview.ask(preview=True)`` over the query service), shows them, then replaces them with the
full answer; a query without a view asks none."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.ground.review import RunReview
from tests.nodes.conftest import region_features, tiny_camera, tiny_run  # noqa: F401  (fixtures)

pytestmark = pytest.mark.timeout(120)


# the page's theme call (viser's own deprecation, not this feature's)
@pytest.mark.filterwarnings("ignore:`control_layout` is deprecated:DeprecationWarning")
def test_the_page_shows_a_small_preview_then_the_full_answer(tiny, tiny_run, monkeypatch):  # noqa: F811
    from olsplat_nodes.ground.page import GroundPage
    from olsplat_nodes.query import service

    monkeypatch.setattr(service, "PREVIEW_MAX_SIDE", 160)  # the tiny views are 320 px wide
    scene, _ = tiny
    review = RunReview(tiny_run, scene / "map" / "point_cloud.ply", 1000)
    asked = []
    ask = review.ask
    monkeypatch.setattr(review, "ask", lambda *a, **k: asked.append(ask(*a, **k)) or asked[-1])
    page = GroundPage(review, port=0)
    try:
        review.refresh()
        page.refresh()  # the page's poll: the map and its one view
        page.view_choice.value = review.cameras()[0].name  # no text yet: nothing asked
        page.query_text.value = "parking lot"
        asked.clear()
        page._ask()
        preview, full = asked
        assert preview.status == full.status == "ok", (preview.message, full.message)
        assert preview.preview and not full.preview and page.previews_shown == 1
        assert preview.heatmap_picture.shape[1] == 160 and full.heatmap_picture.shape[1] == 320
        assert preview.instances == [] and preview.margin is None and full.margin is not None and full.instances
        assert "preview at 160x120" in preview.message
        assert np.array_equal(page.heatmap_image.image, full.heatmap_picture) and page.answer is full
        asked.clear()
        page.view_choice.value = "(none)"
        page._ask()
        assert asked and not any(a.preview for a in asked) and page.previews_shown == 1
    finally:
        page.server.stop()
        review.close()
