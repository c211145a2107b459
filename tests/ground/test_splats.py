"""The page's pure parts: decimation, splat covariances and colours, query text checks."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.ground.colours import RAMP, UNOBSERVED, relevance_colours
from olsplat_nodes.ground.review import query_text_problem, split_negatives
from olsplat_nodes.query.answer import QueryFeatures
from olsplat_nodes.query.splats import browser_splats, decimate, pack_splats, relevance_margin, unpack_splats
from olsplat_nodes.scene import Gaussians
from olsplat_nodes.scene.rotations import quat_to_rotmat


def random_gaussians(n: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(
        means=rng.normal(0, 10, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        log_scales=rng.normal(-1, 0.7, (n, 3)),
        opacity_logits=rng.normal(0, 2, n),
        sh=rng.normal(0, 0.5, (n, 1, 3)),
    )


def test_decimation_keeps_the_most_opaque_and_largest():
    g = random_gaussians(2000)
    keep = decimate(g, 300)
    assert len(keep) == 300 and np.all(np.diff(keep) > 0)
    # the plain definition, one Gaussian at a time
    importance = []
    for i in range(len(g)):
        opacity = 1 / (1 + np.exp(-float(g.opacity_logits[i])))
        s = sorted(np.exp(g.log_scales[i].astype(np.float64)))
        importance.append(opacity * s[1] * s[2])
    threshold = sorted(importance, reverse=True)[299]
    assert all(importance[i] >= threshold for i in keep)
    assert np.array_equal(decimate(g, 300), keep)  # the same choice every time
    assert np.array_equal(decimate(g, 5000), np.arange(2000))
    assert len(decimate(g, 0)) == 0


def test_splat_covariances_are_r_s_s_r():
    g = random_gaussians(50, seed=3)
    s = browser_splats(g, 20)
    for row, i in enumerate(s.ids):
        r = quat_to_rotmat(g.quats[i])
        scale = np.diag(np.exp(g.log_scales[i].astype(np.float64)))
        np.testing.assert_allclose(s.covariances[row], r @ scale @ scale @ r.T, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(s.centers[row], g.means[i])
    assert s.rgbs.min() >= 0 and s.rgbs.max() <= 1 and s.opacities.shape == (20, 1)
    assert "20 of 50 Gaussians drawn" in s.caption
    assert "all 50" in browser_splats(g, 50).caption


def test_relevance_colours_span_the_ramp_and_grey_the_unobserved():
    colours = relevance_colours(np.array([-1.0, -0.2, 0.0, 0.2, 5.0, np.nan]))
    np.testing.assert_allclose(colours[0], RAMP[0])
    np.testing.assert_allclose(colours[1], RAMP[0])
    np.testing.assert_allclose(colours[2], RAMP[2])
    np.testing.assert_allclose(colours[3], RAMP[-1])
    np.testing.assert_allclose(colours[4], RAMP[-1])
    np.testing.assert_allclose(colours[5], UNOBSERVED)


def test_query_texts_the_page_refuses_with_a_sentence():
    assert query_text_problem("red roof buildings", ["road"]) is None
    assert "empty" in query_text_problem("   ", ["road"])
    assert "10,000 characters" in query_text_problem("x" * 10_000, ["road"])
    assert "control characters" in query_text_problem("roof\x00\x1b[31m", ["road"])
    assert "a negative" in query_text_problem("roof", ["road\x07"])
    assert "33 negatives" in query_text_problem("roof", [f"n{i}" for i in range(33)])
    assert split_negatives(" road, ,trees ,") == ["road", "trees"]


def test_splats_packed_for_the_wire_come_back_within_a_colour_step():
    s = browser_splats(random_gaussians(300, seed=5), 200)
    wire = pack_splats(s)
    assert {k: v.dtype.str for k, v in wire.items()} == {
        "centers": "<f4",
        "covariances": "<f4",
        "rgbs": "|u1",
        "opacities": "|u1",
    }
    assert sum(v.nbytes for v in wire.values()) == 40 * 200
    back = unpack_splats(**wire, total=300)
    np.testing.assert_array_equal(back.centers, s.centers)
    np.testing.assert_array_equal(back.covariances, s.covariances)  # symmetric: the triangle holds it all
    assert np.abs(back.rgbs - s.rgbs).max() <= 0.5 / 255 + 1e-7
    assert np.abs(back.opacities - s.opacities).max() <= 0.5 / 255 + 1e-7
    assert back.total == 300 and np.array_equal(back.ids, np.arange(200))
    try:
        unpack_splats(wire["centers"], wire["covariances"][:5], wire["rgbs"], wire["opacities"], 300)
    except ValueError as exc:
        assert "covariances" in str(exc)
    else:
        raise AssertionError("a short covariance array was accepted")


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def test_relevance_margin_is_the_query_minus_the_best_negative_per_splat():
    rng = np.random.default_rng(2)
    n, d, k = 400, 16, 12
    texts = unit(rng.normal(size=(4, d)))  # the query, then three negatives
    observed = rng.random(n) < 0.7
    ids = np.sort(rng.choice(n, 150, replace=False))
    dense = unit(rng.normal(size=(n, d)))
    dense[~observed] = 0.0
    centres = unit(rng.normal(size=(k, d)))
    codes = rng.integers(0, k, n).astype(np.int32)
    codes[~observed] = -1
    for features, feature_of in [
        (QueryFeatures(dense), lambda g: dense[g]),
        (QueryFeatures(centres, codes), lambda g: centres[codes[g]]),
    ]:
        margin = relevance_margin(features, observed, ids, texts)
        for row, g in enumerate(ids):  # the definition, one splat at a time
            if not observed[g]:
                assert np.isnan(margin[row])
                continue
            cos = [float(np.dot(feature_of(g), t)) for t in texts]
            assert abs(margin[row] - (cos[0] - max(cos[1:]))) < 1e-5
