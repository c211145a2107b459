"""The next view rendered while this one is observed (``method.render_ahead``): a render made
ahead on the worker thread, while the main thread runs the observations' parallel kernels, gives
the same observations bit for bit as the per-view step's own render; a render for another view
is dropped, and one that failed ahead is made again where its error is handled."""

from __future__ import annotations

from dataclasses import replace

import numba
import numpy as np
import pytest

from olsplat_nodes.method import MethodParams, view_observations
from olsplat_nodes.method.render_ahead import SAFE_LAYERS, RenderAhead
from olsplat_nodes.method.view_step import render_view
from olsplat_nodes.scene import Camera

from ..conftest import camera_for, random_gaussians
from .test_view_step import _regions


def _moved(camera: Camera, name: str, dx: float) -> Camera:
    pose = camera.world_from_camera.copy()
    pose[0, 3] += dx
    return Camera(name, camera.width, camera.height, camera.K, pose, camera.dist)


def _same(a, b) -> None:
    for field in ("gaussians", "strength", "offsets", "slots", "weights"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)


def test_parallel_kernels_on_two_threads_are_allowed_only_by_a_thread_safe_layer():
    render_view(random_gaussians(50, 0, seed=3), camera_for("PINHOLE_CENTRED", 16, 12), MethodParams().resolve())
    assert RenderAhead.available() == (numba.threading_layer() in SAFE_LAYERS)


@pytest.mark.parametrize("settings", [{}, {"topk_scale": 0.5}])
def test_a_view_rendered_ahead_gives_the_observations_of_its_own_render(settings):
    if not RenderAhead.available():
        pytest.skip(f"numba's threading layer {numba.threading_layer()} is not thread-safe")
    method = MethodParams(**settings).resolve()
    gaussians = random_gaussians(4000, 0, seed=4)
    first = camera_for("PINHOLE_CENTRED", 96, 72)
    views = [first, _moved(first, "second", 0.05), _moved(first, "third", -0.05)]
    label_maps, bank = _regions(first.height, first.width, seed=4)
    alone = [view_observations(gaussians, c, label_maps, bank, method)[0] for c in views]

    ahead = RenderAhead(gaussians, method, threads=2)
    try:
        got = []
        for i, camera in enumerate(views):  # as the accumulator: start the next, then observe this one
            rendered = ahead.take(camera)
            assert (rendered is None) == (i == 0)
            if i + 1 < len(views):
                ahead.start(views[i + 1])
            got.append(view_observations(gaussians, camera, label_maps, bank, method, rendered=rendered)[0])
    finally:
        ahead.close()
    assert ahead.used == 2 and ahead.missed == 0
    for a, b in zip(alone, got, strict=True):
        _same(a, b)
    assert min(len(o) for o in got) > 100


def test_renders_are_taken_in_order_and_those_of_views_passed_over_are_dropped():
    method = MethodParams().resolve()
    gaussians = random_gaussians(500, 0, seed=5)
    first = camera_for("PINHOLE_CENTRED", 48, 36)
    second, third = _moved(first, "second", 0.1), _moved(first, "third", 0.2)
    same_name = _moved(first, first.name, 0.1)  # the same name, another pose: not the same view
    ahead = RenderAhead(gaussians, method, threads=1)
    try:
        ahead.start(first)
        ahead.start(second)  # the view in hand's, then the next one's: both pending
        ahead.start(first)  # already pending: not started twice
        assert [c.name for c, _ in ahead.pending] == [first.name, "second"] and ahead.missed == 0
        assert ahead.take(same_name) is None and len(ahead.pending) == 2  # not that view: nothing dropped
        view = ahead.take(second)  # the first view was passed over: its render is dropped
        assert view is not None and ahead.used == 1 and ahead.missed == 1 and ahead.pending == []
        np.testing.assert_array_equal(view.camera.world_from_camera, second.world_from_camera)
        ahead.start(first)
        ahead.start(second)
        ahead.start(third)  # three at once: the oldest goes
        assert [c.name for c, _ in ahead.pending] == ["second", "third"] and ahead.missed == 2
        assert ahead.take(second) is not None and ahead.take(third) is not None and ahead.used == 3
    finally:
        ahead.close()
    label_maps, bank = _regions(first.height, first.width)
    with pytest.raises(ValueError, match="render given is of view 'ahead'"):
        wrong = render_view(gaussians, _moved(first, "ahead", 0.0), method)
        view_observations(gaussians, first, label_maps, bank, method, rendered=wrong)


def test_a_render_that_failed_ahead_is_made_again_where_its_error_is_handled():
    """The per-view step refuses a smaller Top-K render for VALA's centre features (a method the
    parameters would refuse too, made here by hand): ahead, the error is kept quiet and the view
    rendered again by the per-view step, which raises it as it always did."""
    vala = MethodParams(method="vala").resolve()
    method = replace(vala, raster=replace(vala.raster, topk_scale=0.5))
    gaussians = random_gaussians(300, 0, seed=6)
    camera = camera_for("PINHOLE_CENTRED", 48, 36)
    ahead = RenderAhead(gaussians, method, threads=1)
    try:
        ahead.start(camera)
        assert ahead.take(camera) is None and ahead.missed == 1
    finally:
        ahead.close()
    label_maps, bank = _regions(camera.height, camera.width)
    with pytest.raises(ValueError, match="topk_scale applies to the pixel-weighted view features only"):
        view_observations(gaussians, camera, label_maps, bank, method)


def test_an_offline_run_renders_ahead_and_makes_the_map_it_makes_without(tiny, tmp_path, monkeypatch):
    import shutil

    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.method import named_method
    from olsplat_nodes.pipeline import Scene, aggregate_scene
    from olsplat_nodes.storage import LanguageMap

    if not RenderAhead.available():
        pytest.skip(f"numba's threading layer {numba.threading_layer()} is not thread-safe")
    taken = []
    original = RenderAhead.take

    def counted(self, camera):
        view = original(self, camera)
        taken.append(view is not None)
        return view

    maps = {}
    for label in ("ahead", "alone"):
        shutil.copytree(tiny[0], tmp_path / label / "scene")
        with monkeypatch.context() as patch:
            patch.setattr(RenderAhead, "take", counted)
            if label == "alone":
                patch.setattr(RenderAhead, "available", staticmethod(lambda: False))
            scene = Scene.open(tmp_path / label / "scene")
            aggregate_scene(scene, named_method("outlangsplat"), encoder_from_spec(), tmp_path / label / "out")
        maps[label] = LanguageMap.load(tmp_path / label / "out" / "language_map.npz")
        if label == "ahead":  # every view but the first was rendered ahead
            assert len(taken) == len(scene.cameras) and sum(taken) == len(scene.cameras) - 1, taken
    assert len(taken) == len(scene.cameras)  # none taken without it
    np.testing.assert_array_equal(maps["ahead"].observed, maps["alone"].observed)
    np.testing.assert_array_equal(maps["ahead"].features, maps["alone"].features)
    assert maps["ahead"].observed.sum() > 1000
