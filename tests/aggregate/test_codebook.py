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


def _fit_by_the_first_rule(features, k, sample, seed=0):
    """The rule as first written (a float32 copy of every row, then the sample): the oracle that
    the bounded-memory fit must equal."""
    from olsplat_nodes.aggregate.codebook import _seed_plus_plus

    unit = np.asarray(features, np.float32)
    rows = unit[np.linalg.norm(unit, axis=1) > 0]
    rng = np.random.default_rng(seed)
    data = rows[rng.choice(len(rows), min(sample, len(rows)), replace=False)]
    centres = _seed_plus_plus(data, min(k, len(data)), rng)
    for _ in range(15):
        codes = assign(data, centres)
        sums = np.zeros_like(centres)
        np.add.at(sums, codes, data)
        norms = np.linalg.norm(sums, axis=1, keepdims=True)
        empty = norms[:, 0] == 0
        centres = np.where(empty[:, None], centres, sums / np.maximum(norms, 1e-12))
        if empty.any():
            fit = (data * centres[codes]).sum(1)
            centres[empty] = data[np.argsort(fit)[: int(empty.sum())]]
    return centres.astype(np.float32)


def test_a_float16_map_fits_and_compresses_as_its_float32_copy_did():
    rng = np.random.default_rng(3)
    features = _unit(rng.normal(size=(3000, 24))).astype(np.float16)
    features[rng.random(3000) < 0.3] = 0  # unobserved rows
    centres = fit_codebook(features, 12, sample=1500)
    np.testing.assert_array_equal(centres, _fit_by_the_first_rule(features, 12, 1500))
    np.testing.assert_array_equal(compress(features, centres), compress(features.astype(np.float32), centres))


def test_saving_a_codebook_map_copies_no_float32_map(tmp_path):
    """LanguageMap.save(codebook=K) of a float16 map never holds the map as float32: its peak
    traced allocation stays below the size of that copy (the large map: 1.3 GB more)."""
    import tracemalloc

    from olsplat_nodes.storage import LanguageMap

    n, d = 400_000, 64
    rng = np.random.default_rng(4)
    features = _unit(rng.normal(size=(n, d)).astype(np.float32)).astype(np.float16)
    language_map = LanguageMap(features, np.ones(n, bool), "test")
    tracemalloc.start()
    try:
        language_map.save(tmp_path / "map.npz", codebook=16)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    float32_copy = n * d * 4  # 102 MB
    assert peak < 0.6 * float32_copy, f"peak {peak / 2**20:.0f} MB"
    assert LanguageMap.load(tmp_path / "map.npz").form == "codebook"
