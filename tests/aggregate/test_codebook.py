"""The language-map codebook against brute force."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.aggregate.codebook import assign, compress, decompress, fit_codebook


def _unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_assign_matches_brute_force_over_chunks():
    rng = np.random.default_rng(0)
    features, centres = _unit(rng.normal(size=(1000, 16))), _unit(rng.normal(size=(37, 16)))
    brute = np.array([max(range(37), key=lambda c: float(f @ centres[c])) for f in features])
    assert np.array_equal(assign(features, centres, chunk=97), brute)


def test_fit_recovers_well_separated_clusters():
    rng = np.random.default_rng(1)
    truth = np.eye(8, 32)  # 8 orthogonal directions
    members = rng.integers(0, 8, 4000)
    features = _unit(truth[members] + 0.05 * rng.normal(size=(4000, 32))).astype(np.float32)
    centres = fit_codebook(features, 8, sample=2000)
    assert np.sort((centres @ truth.T).max(0)).min() > 0.99  # every true direction has a centre
    codes = compress(features, centres)
    restored = decompress(codes, centres)
    assert (np.sum(restored * features, axis=1) > 0.9).all()  # noise 0.05 in 32 dims: cos ~0.96
    assert (np.argmax(centres @ truth.T, axis=1)[codes] == members).all()


def test_unobserved_rows_stay_zero():
    features = np.zeros((5, 4), np.float32)
    features[:3] = _unit(np.array([[1, 0, 0, 0], [0, 1, 0, 0], [1, 1, 0, 0]], np.float32))
    centres = fit_codebook(features, 2)
    codes = compress(features, centres)
    assert (codes[3:] == 65535).all() and (codes[:3] < 2).all()
    assert not decompress(codes, centres)[3:].any()
