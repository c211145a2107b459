"""The map a query reads (``query.service.MapService``), without any socket: on the tiny simulated
flight's run folder (one view, map version 1), the states a run folder goes through (no map, a
first version, a newer one, a map of another prior refused with its reason), answers equal to
``answer_query``'s on the same inputs, the splats' margin equal to ``relevance_margin``, the
refusals, and ``close()`` leaving no background thread behind."""

from __future__ import annotations

import shutil
import threading

import numpy as np
import pytest

from olsplat_nodes.query.service import NO_MAP, MapService, text_problem
from tests.nodes.conftest import ENCODE_VIEW

pytestmark = pytest.mark.timeout(300)
NEGATIVES = ["road", "trees", "lawn"]


def service_over(scene, map_dir, views_dir, name: str, **settings) -> MapService:
    return MapService(scene / "map" / "point_cloud.ply", map_dir, views_dir, name=name, **settings)


def alive(service: MapService) -> list[str]:
    """The names of the service's background threads still running."""
    own = [t.name for t in service.threads() if t.is_alive()]
    return own + [t.name for t in threading.enumerate() if t.name.startswith(f"{service.name}-")]


@pytest.fixture(scope="module")
def served(tiny, tiny_run):
    """A service over the tiny run (read only) with its warm-up done, and (language map, encoder)."""
    from olsplat_nodes.query.answer import encoder_for_map
    from olsplat_nodes.storage import LanguageMap, latest_map

    scene, _ = tiny
    service = service_over(scene, tiny_run / "map", tiny_run / "views", "svc-answers", heatmap_cache_mb=0)
    assert service.refresh() is True
    service.warm_up.join()  # the voxel index made: answer_query below gets the same one
    language_map = LanguageMap.load(latest_map(tiny_run / "map")["path"])
    yield service, language_map, encoder_for_map(language_map)
    service.close()


def test_no_map_then_each_newer_version_and_close_leaves_no_thread(tiny, tiny_run, tmp_path):
    from olsplat_nodes.storage import LanguageMap, latest_map, write_snapshot

    scene, _ = tiny
    service = service_over(scene, tmp_path / "map", tmp_path / "views", "svc-versions")
    try:
        assert service.refresh() is False and service.version == 0 and service.language_map is None
        answer = service.answer("red roof buildings", NEGATIVES, view=ENCODE_VIEW)
        assert (answer.status, answer.message, answer.version, answer.answer) == ("no_map", NO_MAP, 0, None)
        values = service.status_values()
        assert values["map_version"] == 0 and values["query_warm"] == 0 and service.cameras() == []

        # the run's first view and snapshot appear
        shutil.copytree(tiny_run / "views", tmp_path / "views")
        shutil.copytree(tiny_run / "map", tmp_path / "map")
        assert service.refresh() is True and service.version == 1
        assert [c.name for c in service.cameras()] == [ENCODE_VIEW]
        state = service.state
        assert (state.version, state.views_in_map, state.final) == (1, 1, True)
        assert state.observed == int(service.language_map.observed.sum()) > 0
        assert service.refresh() is False  # nothing new

        # the refiner writes version 2: picked up without a new service
        language_map = LanguageMap.load(latest_map(tmp_path / "map")["path"])
        write_snapshot(tmp_path / "map", 2, language_map, {"views": 1, "final": False}, None)
        assert service.refresh(views=False) is True and service.version == 2 and not service.state.final
        assert service.answer("red roof buildings", NEGATIVES).status == "ok"
        assert service.warm_query is not None and service.warm_query.result() > 0
        assert service.status_values()["query_warm"] == 1
    finally:
        service.close()
    assert service.threads() and alive(service) == []


def test_a_map_of_another_gaussian_count_is_refused_with_the_reason(tiny, tiny_run, tmp_path):
    from olsplat_nodes.storage import LanguageMap, latest_map, write_snapshot

    scene, _ = tiny
    good = LanguageMap.load(latest_map(tiny_run / "map")["path"])
    other = LanguageMap(good.features[:-5], good.observed[:-5], good.encoder)  # another prior's map
    record = write_snapshot(tmp_path / "map", 1, other, {"views": 1}, None)
    service = service_over(scene, tmp_path / "map", tmp_path / "views", "svc-refused")
    try:
        assert service.refresh() is False and service.version == 0
        n = len(good)
        assert service.refusal == f"{record['path']}: the map has {n - 5} Gaussians, the prior map {n}"
        assert service.answer("road", NEGATIVES).status == "no_map"
        assert service.refresh() is False and service.refusal is not None  # refused once, said until replaced

        write_snapshot(tmp_path / "map", 2, good, {"views": 1}, None)
        assert service.refresh() is True and service.version == 2 and service.refusal is None
    finally:
        service.close()
    assert alive(service) == []


def test_an_answer_with_a_view_is_answer_querys_on_the_same_inputs(tiny, served):
    from olsplat_nodes.query.answer import answer_query
    from olsplat_nodes.storage import load_views

    service, language_map, encoder = served
    camera = next(v.camera for v in service.views() if v.camera.name == ENCODE_VIEW)
    for text in ("red roof buildings", "parking lot"):
        result = service.answer(text, NEGATIVES, view=ENCODE_VIEW)
        assert result.status == "ok" and result.version == 1 and result.camera is camera
        expected = answer_query(
            language_map,
            service.gaussians,
            encoder,
            text,
            NEGATIVES,
            camera,
            cluster_radius=service.cluster_radius,
            voxel_index=service.voxel_index,
        )
        got = result.answer
        assert (got.text, got.negatives, got.chosen_count) == (expected.text, expected.negatives, expected.chosen_count)
        np.testing.assert_array_equal(got.chosen, expected.chosen)
        assert got.instances == expected.instances and got.regions == expected.regions
        for name in ("heatmap", "negative_heatmaps", "alpha", "mask"):
            np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)
        photo = next(v for v in load_views(service.views_dir) if v.camera.name == ENCODE_VIEW).image()
        np.testing.assert_array_equal(result.photo, photo)

    # without the heatmap: the same 2D regions, no heatmap, mask or photo
    bare = service.answer("parking lot", NEGATIVES, view=ENCODE_VIEW, heatmap=False)
    assert bare.answer.heatmap is None and bare.answer.mask is None and bare.photo is None
    assert bare.answer.regions == got.regions
    # a threshold instead of the negatives; NaN: the negatives again
    high = service.answer("parking lot", NEGATIVES, view=ENCODE_VIEW, threshold=0.99).answer
    assert high.mask is not None and not high.mask.any()
    nan = service.answer("parking lot", NEGATIVES, view=ENCODE_VIEW, threshold=float("nan")).answer
    np.testing.assert_array_equal(nan.mask, got.mask)


def test_a_preview_is_the_view_small_drawn_from_the_decimated_map(tiny, tiny_run, monkeypatch):
    """A preview: the view scaled to PREVIEW_MAX_SIDE, no 3D answer and no margin, its heatmap
    rendered from the map's PREVIEW_MAX_GAUSSIANS most opaque and largest Gaussians (equal to
    rendering that subset as a map of its own with its features), its pictures in a cache of
    their own (a full view's stays); refused without a view."""
    from olsplat_nodes.query import service as module
    from olsplat_nodes.query.answer import encoder_for_map
    from olsplat_nodes.query.heatmap import relevancy_mask, render_heatmaps
    from olsplat_nodes.query.splats import decimate

    monkeypatch.setattr(module, "PREVIEW_MAX_SIDE", 160)  # the tiny views are 320 px wide
    monkeypatch.setattr(module, "PREVIEW_MAX_GAUSSIANS", 8000)  # of the tiny map's ~26,000
    scene, _ = tiny
    service = service_over(scene, tiny_run / "map", tiny_run / "views", "svc-preview", heatmap_cache_mb=64)
    try:
        assert service.refresh() is True
        service.warm_up.join()
        full = service.answer("parking lot", NEGATIVES, view=ENCODE_VIEW, splats=1000)
        preview = service.answer("parking lot", NEGATIVES, view=ENCODE_VIEW, splats=1000, preview=True)
        assert preview.status == "ok" and (preview.camera.width, preview.camera.height) == (160, 120)
        got = preview.answer
        assert got.chosen_count == -1 and got.instances == [] and preview.margin is None
        assert got.heatmap.shape == got.mask.shape == preview.photo.shape[:2] == (120, 160)
        assert full.answer.instances and full.margin is not None and full.answer.heatmap.shape == (240, 320)

        drawn, ids = service.preview_map()
        np.testing.assert_array_equal(ids, decimate(service.gaussians, 8000))
        assert len(drawn) == 8000 and drawn.sh.shape[1] == 1  # no colours kept
        features = service.loaded.features
        assert features.rows is None  # a float16 map: row g is Gaussian g's feature
        texts = encoder_for_map(service.language_map).encode_text(["parking lot", *NEGATIVES])
        # the subset as a map of its own, with its own rows of features
        own = np.asarray(features.table, np.float32)[ids]
        maps, alpha = render_heatmaps(service.gaussians.subset(ids), own, texts, preview.camera)
        np.testing.assert_allclose(got.heatmap, maps[0], atol=2e-5)
        np.testing.assert_array_equal(got.mask, relevancy_mask(maps[0], maps[1:], alpha))
        # the full view's features stay cached: the preview went to a cache of its own
        assert service.feature_images.misses == 1 and service.preview_images.misses == 1
        service.answer("road", NEGATIVES, view=ENCODE_VIEW)
        service.answer("road", NEGATIVES, view=ENCODE_VIEW, preview=True)
        assert service.feature_images.hits == 1 and service.preview_images.hits == 1

        refused = service.answer("parking lot", NEGATIVES, preview=True)
        assert refused.status == "bad_request" and "give a view" in refused.message
    finally:
        service.close()


def test_the_splats_margin_is_relevance_margin(served):
    from olsplat_nodes.query.answer import QueryFeatures
    from olsplat_nodes.query.splats import browser_splats, relevance_margin

    service, language_map, encoder = served
    result = service.answer("red roof buildings", NEGATIVES, splats=3000)
    assert result.status == "ok" and result.margin is not None and result.margin.shape == (3000,)
    ids = browser_splats(service.gaussians, 3000).ids
    np.testing.assert_array_equal(service.splats(3000).ids, ids)
    texts = encoder.encode_text(["red roof buildings", *NEGATIVES])
    expected = relevance_margin(QueryFeatures.of(language_map), language_map.observed, ids, texts)
    np.testing.assert_array_equal(result.margin, expected)
    np.testing.assert_array_equal(service.margin(result, service.splats(3000)), expected)
    assert np.isnan(expected).any() and np.isfinite(expected).any()  # one view observes part of the map
    assert service.answer("road", NEGATIVES).margin is None  # not asked: not made


def test_refusals_come_back_as_a_status_with_the_reason(tiny, tiny_run, served):
    service, _, _ = served
    cases = [
        (("  ", NEGATIVES), {}, "the query text is empty"),
        (("x" * 201, NEGATIVES), {}, "the query text is longer than 200 characters"),
        (("road", [f"thing {i}" for i in range(33)]), {}, "33 negatives; at most 32 per query"),
        (("road", ["x" * 201]), {}, "a negative is longer than 200 characters"),
        (("road", NEGATIVES), {"splats": 600_000}, "splats must be 0..500,000, got 600,000"),
    ]
    for args, options, message in cases:
        result = service.answer(*args, **options)
        assert (result.status, result.message, result.answer) == ("bad_request", message, None)
    unknown = service.answer("road", NEGATIVES, view="nowhere.jpg")
    assert unknown.status == "bad_request" and "no view 'nowhere.jpg'" in unknown.message

    scene, _ = tiny
    small = service_over(scene, tiny_run / "map", tiny_run / "views", "svc-limits", max_reply_mb=0.5)
    try:
        small.refresh()
        big = small.answer("road", NEGATIVES, view=ENCODE_VIEW)
        assert big.message == f"view {ENCODE_VIEW} is 320x240: its heatmap reply would be 0.6 MB, over max_reply_mb 0.5"
        assert small.answer("road", NEGATIVES, view=ENCODE_VIEW, heatmap=False).status == "ok"
    finally:
        small.close()


def test_text_problems_in_order_and_control_characters_only_when_asked():
    assert text_problem("red roof buildings", ["road"]) is None
    assert text_problem("  ", ["x" * 500]).kind == "empty"
    assert text_problem("roof\x07", ["road"]) is None  # the query server's rule: no control check
    problem = text_problem("roof\x07", ["road"], control=True)
    assert (problem.kind, problem.subject) == ("control", "query")
    problem = text_problem("roof", ["x" * 300] * 40)  # too many before too long
    assert (problem.kind, problem.size, problem.limit) == ("negatives", 40, 32)
    problem = text_problem("roof", ["road", "x" * 300], max_chars=250)
    assert (problem.kind, problem.subject, problem.size, problem.limit) == ("long", "negative", 300, 250)
