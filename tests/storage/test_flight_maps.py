"""Maps per flight: the evidence arrays of a language map on disk (old maps still load), and
``olsplat aggregate --per-flight`` over two real simulated flights."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.storage import LanguageMap
from olsplat_nodes.storage.flights import flight_of


def _evidence_map(n=50, dim=8, seed=0) -> LanguageMap:
    rng = np.random.default_rng(seed)
    observed = rng.random(n) < 0.8
    features = rng.normal(size=(n, dim)) * observed[:, None]
    return LanguageMap(
        (features / np.maximum(np.linalg.norm(features, axis=1, keepdims=True), 1e-9)).astype(np.float16),
        observed,
        "test",
        strength_sum=rng.uniform(0, 9, n).astype(np.float32) * observed,
        view_count=rng.integers(1, 9, n).astype(np.int32) * observed,
        effective_views=rng.uniform(1, 5, n).astype(np.float32) * observed,
        view_spread=np.where(observed, rng.uniform(0, 0.3, n), np.nan).astype(np.float32),
    )


@pytest.mark.parametrize("codebook", [None, 8])
def test_evidence_is_saved_and_loaded(tmp_path, codebook):
    original = _evidence_map()
    original.save(tmp_path / "m.npz", codebook)
    for decode in (True, False):
        loaded = LanguageMap.load(tmp_path / "m.npz", decode=decode)
        assert loaded.has_evidence() and loaded.form == ("codebook" if codebook else "float16")
        for key in ("strength_sum", "view_count", "effective_views", "view_spread"):
            np.testing.assert_array_equal(getattr(loaded, key), getattr(original, key))
        assert loaded.view_count is not None and loaded.view_count.dtype == np.int32


def test_maps_without_evidence_load_as_before(tmp_path):
    plain = _evidence_map()
    plain.strength_sum = plain.view_count = plain.effective_views = plain.view_spread = None
    plain.save(tmp_path / "plain.npz")
    with zipfile.ZipFile(tmp_path / "plain.npz") as archive:
        assert sorted(archive.namelist()) == ["encoder.npy", "features.npy", "form.npy", "observed.npy", "version.npy"]
    loaded = LanguageMap.load(tmp_path / "plain.npz")
    assert not loaded.has_evidence() and loaded.strength_sum is None
    np.testing.assert_array_equal(loaded.features, plain.features)


def test_partial_or_misshapen_evidence_is_refused(tmp_path):
    partial = _evidence_map()
    partial.view_spread = None
    with pytest.raises(ValueError, match="evidence needs all of"):
        partial.save(tmp_path / "partial.npz")
    whole = _evidence_map()
    whole.save(tmp_path / "whole.npz")
    with np.load(tmp_path / "whole.npz") as data:
        arrays = {key: data[key] for key in data.files}
    arrays["view_count"] = arrays["view_count"][:-1]
    np.savez(tmp_path / "short.npz", **arrays)
    with pytest.raises(SceneFormatError, match=r"short\.npz.*evidence arrays"):
        LanguageMap.load(tmp_path / "short.npz")


def test_flight_of_a_view_name():
    assert flight_of("f1/frame_0003.jpg") == "f1" and flight_of("f12/x") == "f12"
    assert flight_of("frame_0003.jpg") == "f0" and flight_of("flight7_frame_0001.jpg") == "f0"


def test_per_flight_maps_of_two_simulated_flights(tmp_path, capsys):
    """``olsplat aggregate --scene A --scene B --per-flight``: flight f0's map is, to the bit, the
    map of ``olsplat aggregate --scene A`` (the same views refined alone, in the same order, by
    the same kernels), f1's that of B; the combined map is written as before."""
    for out, extra in (("A", []), ("B", ["--flight-seed", "1"])):
        make = ["sim", "make", "--preset", "tiny", "--seed", "0", "--views", "3", "--out", str(tmp_path / out)]
        assert main([*make, *extra]) == 0
    both = ["aggregate", "--scene", str(tmp_path / "A"), "--scene", str(tmp_path / "B")]
    assert main([*both, "--out", str(tmp_path / "AB"), "--per-flight"]) == 0
    printed = capsys.readouterr().out
    assert "flight f1: 3 views" in printed and "change f0 -> f1: " in printed, printed
    assert main(["aggregate", "--scene", str(tmp_path / "A"), "--out", str(tmp_path / "Aonly")]) == 0
    index = json.loads((tmp_path / "AB" / "flights" / "flights.json").read_text())
    assert [(r["flight"], r["views"], r["scene"]) for r in index["flights"]] == [
        ("f0", 3, str((tmp_path / "A").resolve())),
        ("f1", 3, str((tmp_path / "B").resolve())),
    ]
    ours = LanguageMap.load(tmp_path / "AB" / "flights" / "f0" / "language_map.npz")
    alone = LanguageMap.load(tmp_path / "Aonly" / "language_map.npz")
    np.testing.assert_array_equal(ours.features, alone.features)
    np.testing.assert_array_equal(ours.observed, alone.observed)
    assert ours.encoder == alone.encoder and ours.has_evidence() and not alone.has_evidence()
    assert ours.view_count is not None and ours.view_count.max() <= 3
    np.testing.assert_array_equal(ours.view_count > 0, ours.observed)
    assert (tmp_path / "AB" / "language_map.npz").exists()
