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


def test_the_live_codebook_reassigns_what_changed_and_refits_when_the_map_doubles():
    from olsplat_nodes.aggregate.codebook import LiveCodebook

    rng = np.random.default_rng(2)
    truth = np.eye(6, 16)
    members = rng.integers(0, 6, 900)
    dense = _unit(truth[members] + 0.05 * rng.normal(size=(900, 16))).astype(np.float16)
    features = np.zeros_like(dense)
    observed = np.zeros(900, bool)
    observed[:300] = True
    features[:300] = dense[:300]
    live = LiveCodebook(6, sample=200)
    codes, centres = live.update(features, observed, observed.copy())
    assert live.fits == 1 and np.array_equal(codes, compress(features.astype(np.float32), centres))
    assert (codes[300:] == 65535).all()
    # a pass that recomputes 100 rows (and observes 100 new ones): only those are assigned anew
    changed = np.zeros(900, bool)
    changed[250:400] = True
    features[300:400] = dense[300:400]
    features[250:300] = dense[np.arange(50) + 600]  # rows whose features moved to another cluster
    observed[300:400] = True
    before = codes.copy()
    codes, same_centres = live.update(features, observed, changed)
    assert live.fits == 1 and same_centres is centres
    assert np.array_equal(codes[~changed], before[~changed])
    assert np.array_equal(codes[changed], compress(features[changed].astype(np.float32), centres))
    # twice the Gaussians observed since the fit: fitted again, every row assigned
    observed[:] = True
    features[:] = dense
    codes, new_centres = live.update(features, observed, np.zeros(900, bool))
    assert live.fits == 2 and np.array_equal(codes, compress(features.astype(np.float32), new_centres))
