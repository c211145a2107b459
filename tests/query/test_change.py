"""query/change.py on made-up maps: the clustering is the ordinary query's, the object rule, the
ranking, a text's moves against a dense numpy oracle, the change negatives, the change heatmap."""

from __future__ import annotations

import math

import numpy as np
import pytest

from olsplat_nodes.aggregate.codebook import compress, decompress, fit_codebook
from olsplat_nodes.query._reference import instances_in_3d_bfs
from olsplat_nodes.query.change import (
    ChangeParams,
    change_instances,
    change_negatives,
    cluster_labels,
    render_change,
    text_change,
    text_moves,
)
from olsplat_nodes.query.localize import ground_density, instances_in_3d
from olsplat_nodes.storage import LanguageMap
from tests.conftest import camera_for, random_gaussians


def _town(seed=0):
    """[N, 3] centres: a flat 100 m square of ground plus two blobs, and scores: NaN for two
    thirds (unknown), low noise elsewhere, high on the blobs (the changes)."""
    rng = np.random.default_rng(seed)
    ground = rng.uniform(0, 100, (6000, 3)) * [1, 1, 0.02]
    car = rng.normal([30, 30, 1], [1.5, 0.8, 0.4], (60, 3))
    shed = rng.normal([70, 20, 1], 1.0, (120, 3))
    means = np.concatenate([ground, car, shed])
    score = np.where(rng.random(len(means)) < 0.35, rng.uniform(0, 1.2, len(means)), np.nan).astype(np.float32)
    score[6000:6060] = rng.uniform(1.5, 3.5, 60)
    score[6060:] = rng.uniform(2.0, 4.0, 120)
    return means, score


def test_cluster_labels_are_the_query_clustering():
    """Each cluster of ``cluster_labels`` is an instance of ``instances_in_3d`` (same count, box and
    centre) and of the brute-force oracle, on the same selection."""
    means, score = _town()
    selected = np.flatnonzero(score > 1.0)
    labels = cluster_labels(means[selected], 3.0, 5)
    ours = []
    for label in np.unique(labels[labels >= 0]):
        points = means[selected[labels == label]]
        if len(points) >= 5:
            ours.append((len(points), *points.min(0), *points.max(0)))
    for reference in (instances_in_3d(means, selected, 3.0, 5), instances_in_3d_bfs(means, selected, 3.0, 5)):
        theirs = sorted((i.gaussians, *i.box_min, *i.box_max) for i in reference)
        assert len(theirs) == len(ours)
        for mine, its in zip(sorted(ours), theirs, strict=True):
            assert mine == pytest.approx(its)
    assert len(ours) >= 2


def test_change_instances_keep_the_clear_clusters_ranked():
    means, score = _town()
    params = ChangeParams(candidate=1.2, object_score=1.8, min_gaussians=10, cluster_radius=3.0, min_points=5)
    found = change_instances(means, score, params)
    assert [round(i.centre[0]) for i in found] == [70, 30]  # the shed: more members at a higher median
    shed, car = found
    assert set(shed.members) <= set(range(6060, 6180)) and len(shed.members) == shed.gaussians
    assert shed.score == pytest.approx(float(np.median(score[shed.members])))
    assert shed.rank_value > car.rank_value
    # the object threshold: the car's median is ~2.5, the shed's ~3
    assert [round(i.centre[0]) for i in change_instances(means, score, ChangeParams(1.2, 2.7, 10, 3.0, 5))] == [70]
    # the size: neither has 500 members
    assert change_instances(means, score, ChangeParams(1.2, 1.8, 500, 3.0, 5)) == []
    # unknown is never a candidate, whatever the cuts
    assert change_instances(means, np.full(len(means), np.nan, np.float32), ChangeParams(0.0, 0.0, 1, 3.0, 1)) == []
    # among: only these may be candidates
    among = np.zeros(len(means), bool)
    among[6000:6060] = True
    assert [round(i.centre[0]) for i in change_instances(means, score, params, among)] == [30]


def test_the_least_size_is_ground_area_at_the_map_s_density():
    """min_area_m2 counts in square metres of the map's ground (its Gaussians per m² between the
    1st and 99th percentiles of x and y): the same area is more Gaussians on a denser map."""
    means, score = _town()
    width = np.percentile(means[:, :2], 99, axis=0) - np.percentile(means[:, :2], 1, axis=0)
    density = len(means) / float(np.prod(width))
    assert ground_density(means) == pytest.approx(density) and 0.6 < density < 0.7
    assert ground_density(means[:1]) == 0.0
    assert ChangeParams(min_area_m2=100.0).min_members(means) == math.ceil(100.0 * density)  # ~64
    assert ChangeParams(min_area_m2=1.0).min_members(means) == 10  # the fixed count is the floor
    assert ChangeParams(min_area_m2=100.0).min_members(np.concatenate([means, means])) > 120  # twice as dense
    # the car (60 Gaussians) is under 100 m² of this sparse ground, the shed (120) is not
    params = ChangeParams(1.2, 1.8, 10, 3.0, 5, min_area_m2=100.0)
    assert [round(i.centre[0]) for i in change_instances(means, score, params)] == [70]


def test_params_resolved_for_a_map_give_the_same_instances(monkeypatch):
    """``for_map`` turns the least area into a member count and fills in the radius from one
    density: the instances are the unresolved params', resolving again computes nothing, and a
    query server resolves its rules once at start-up (not on every change request)."""
    from olsplat_nodes.query import change
    from olsplat_nodes.query.localize import default_cluster_radius

    means, score = _town()
    params = ChangeParams(1.2, 1.8, 10, 0.0, 5, min_area_m2=100.0)
    rule = params.for_map(means)
    assert rule.min_gaussians == params.min_members(means) == math.ceil(100.0 * ground_density(means))
    assert rule.cluster_radius == default_cluster_radius(means) and rule.min_area_m2 == 0.0
    assert rule.candidate == params.candidate and rule.object_score == params.object_score
    expected = [(i.gaussians, i.centre) for i in change_instances(means, score, params)]
    calls = []
    monkeypatch.setattr(change, "ground_density", lambda m: calls.append(1) or ground_density(m))
    assert rule.for_map(means) is rule and not calls  # resolved: no density pass
    assert [(i.gaussians, i.centre) for i in change_instances(means, score, rule)] == expected and not calls
    change_instances(means, score, params)
    assert len(calls) == 1  # unresolved: one pass for both the radius and the least size


def test_change_params_are_checked():
    with pytest.raises(ValueError, match="candidate <= object_score"):
        ChangeParams(candidate=2.0, object_score=1.0)
    with pytest.raises(ValueError, match="min_gaussians >= 1"):
        ChangeParams(min_gaussians=0)
    with pytest.raises(ValueError, match="min_area_m2"):
        ChangeParams(min_area_m2=-1.0)
    with pytest.raises(ValueError, match=r"need means \[N, 3\] and score \[N\]"):
        change_instances(np.zeros((5, 3)), np.zeros(4, np.float32))


def _flight(features, observed) -> LanguageMap:
    rows = features / np.maximum(np.linalg.norm(features, axis=1, keepdims=True), 1e-9)
    return LanguageMap((rows * observed[:, None]).astype(np.float16), observed, "test")


def _moves_dense(a: LanguageMap, b: LanguageMap, embeddings: np.ndarray, direction: str) -> np.ndarray:
    """The rule of ``text_moves`` in float64 numpy, all rows at once."""
    rise = (b.features.astype(np.float64) - a.features.astype(np.float64)) @ embeddings.astype(np.float64).T
    rise = rise if direction == "appeared" else -rise
    return (rise[:, 0] > 0) & (rise.argmax(1) == 0) & a.observed & b.observed


@pytest.mark.parametrize("direction", ["appeared", "gone"])
def test_text_moves_match_the_dense_rule(direction, monkeypatch):
    import olsplat_nodes.query.change as change

    monkeypatch.setattr(change, "_ROWS", 1000)  # several chunks
    rng = np.random.default_rng(1)
    n, dim = 4500, 16
    a = _flight(rng.normal(size=(n, dim)), rng.random(n) < 0.9)
    b = _flight(rng.normal(size=(n, dim)), rng.random(n) < 0.9)
    embeddings = rng.normal(size=(5, dim))
    embeddings /= np.linalg.norm(embeddings, axis=1, keepdims=True)
    moved = text_moves(a, b, embeddings, direction)  # type: ignore[arg-type]
    expected = _moves_dense(a, b, embeddings, direction)
    # float32 against float64: only near-ties may differ
    assert (moved != expected).sum() <= 2 and 0.1 < moved.mean() < 0.3
    # a codebook map is read through its codes: as its decoded rows
    centres = fit_codebook(b.features, 64)
    coded = LanguageMap(np.zeros((0, dim), np.float16), b.observed, "test", "codebook")
    coded.codes, coded.centres = compress(b.features, centres), centres.astype(np.float16)
    decoded = LanguageMap(decompress(coded.codes, coded.centres), b.observed, "test")
    np.testing.assert_array_equal(
        text_moves(a, coded, embeddings, direction),  # type: ignore[arg-type]
        text_moves(a, decoded, embeddings, direction),  # type: ignore[arg-type]
    )


def test_text_change_keeps_the_moved_change():
    """Two changed blobs, one of whose features moved towards the text: only that one is the
    text's change; the other direction finds none."""
    means, score = _town()
    rng = np.random.default_rng(2)
    dim = 8
    text, other = np.eye(dim)[0], np.eye(dim)[1]
    before = rng.normal(size=(len(means), dim)) * 0.1 + np.eye(dim)[2]
    after = before.copy()
    after[6000:6060] += 2 * text  # the car moved towards the text
    after[6060:] += 2 * other  # the shed towards another
    observed = np.ones(len(means), bool)
    a, b = _flight(before, observed), _flight(after, observed)
    params = ChangeParams(1.2, 1.8, 10, 3.0, 5)
    embeddings = np.stack([text, other, np.eye(dim)[2]])  # the negatives: the other class and what all were
    found = text_change(means, score, a, b, embeddings, "appeared", params)  # type: ignore[arg-type]
    assert [round(i.centre[0]) for i in found] == [30]
    assert text_change(means, score, a, b, embeddings, "gone", params) == []  # type: ignore[arg-type]
    assert [round(i.centre[0]) for i in text_change(means, score, b, a, embeddings, "gone", params)] == [30]  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="direction must be one of"):
        text_moves(a, b, embeddings, "left")  # type: ignore[arg-type]


def test_change_negatives_drop_the_class_a_text_names():
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.query.negatives import vocabulary_negatives

    encoder = encoder_from_spec()
    assert "cars" in vocabulary_negatives("new vehicles", encoder)
    assert "cars" not in change_negatives("new vehicles", encoder)
    assert change_negatives("cars", encoder) == vocabulary_negatives("cars", encoder)  # a named class itself
    assert len(change_negatives("new vehicles", encoder)) == len(vocabulary_negatives("new vehicles", encoder)) - 1


def test_change_heatmap_is_the_mean_score_of_the_scored():
    """A constant score renders as that score wherever scored Gaussians make at least half the
    pixel's weight; unscored Gaussians alone leave NaN; ``among`` counts the others as 0."""
    gaussians = random_gaussians(400, seed=3)
    camera = camera_for("PINHOLE_CENTRED", 64, 48)
    score = np.full(len(gaussians), 2.5, np.float32)
    heat, alpha = render_change(gaussians, score, camera)
    drawn = np.isfinite(heat)
    assert drawn.mean() > 0.2 and np.allclose(heat[drawn], 2.5, atol=1e-4)
    assert (alpha[drawn] > 1e-6).all()
    unknown, _ = render_change(gaussians, np.full(len(gaussians), np.nan, np.float32), camera)
    assert np.isnan(unknown).all()
    none_moved, _ = render_change(gaussians, score, camera, among=np.zeros(len(gaussians), bool))
    assert np.allclose(none_moved[drawn], 0.0)
