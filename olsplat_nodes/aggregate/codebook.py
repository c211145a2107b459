"""A learned codebook for language maps: each Gaussian's unit feature -> the nearest of K centres.

Spherical k-means (cosine similarity, unit centres), fitted on a sample and then applied to
every Gaussian in chunks, so memory stays bounded on million-Gaussian maps. Storage per Gaussian
is one uint16 code instead of D float16 values (K * D float16 for the codebook itself).
``olsplat bench compression`` measures what this costs in query accuracy against float16.
"""

from __future__ import annotations

import numpy as np


def assign(features: np.ndarray, centres: np.ndarray, chunk: int = 65_536) -> np.ndarray:
    """[N, D] unit features, [K, D] unit centres -> [N] int64 index of the most similar centre."""
    codes = np.empty(len(features), np.int64)
    c = centres.astype(np.float32)
    for start in range(0, len(features), chunk):
        codes[start : start + chunk] = (features[start : start + chunk].astype(np.float32) @ c.T).argmax(1)
    return codes


def fit_codebook(
    features: np.ndarray, k: int, iterations: int = 15, sample: int = 100_000, seed: int = 0
) -> np.ndarray:
    """[K, D] float32 unit centres fitted to a sample of the non-zero rows of ``features`` [N, D]
    (unit rows, float16 or float32). Only the sample is copied (as float32): a 5.2M x 64 map's
    float32 copy and its norms would be 2.7 GB more at the peak of an offline run."""
    nonzero = np.flatnonzero(_nonzero_rows(features))
    if len(nonzero) == 0:
        raise ValueError("no observed Gaussian to fit a codebook to")
    rng = np.random.default_rng(seed)
    data = np.asarray(features[nonzero[rng.choice(len(nonzero), min(sample, len(nonzero)), replace=False)]], np.float32)
    k = min(k, len(data))
    centres = _seed_plus_plus(data, k, rng)
    for _ in range(iterations):
        codes = assign(data, centres)
        sums = np.zeros_like(centres)
        np.add.at(sums, codes, data)
        norms = np.linalg.norm(sums, axis=1, keepdims=True)
        empty = norms[:, 0] == 0
        centres = np.where(empty[:, None], centres, sums / np.maximum(norms, 1e-12))
        if empty.any():  # re-seed unused centres on the worst-fitted points
            fit = (data * centres[codes]).sum(1)
            centres[empty] = data[np.argsort(fit)[: int(empty.sum())]]
    return centres.astype(np.float32)


def _nonzero_rows(features: np.ndarray, chunk: int = 262_144) -> np.ndarray:
    """[N] bool: rows of ``features`` [N, D] with a non-zero value, a chunk at a time (no [N, D] temporary)."""
    out = np.empty(len(features), bool)
    for start in range(0, len(features), chunk):
        out[start : start + chunk] = features[start : start + chunk].any(1)
    return out


def _seed_plus_plus(data: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding with the cosine distance 1 - cos: far-apart starting centres."""
    centres = np.empty((k, data.shape[1]), np.float32)
    centres[0] = data[rng.integers(len(data))]
    distance = 1.0 - data @ centres[0]
    for i in range(1, k):
        p = np.maximum(distance, 0.0)
        total = p.sum()
        pick = rng.choice(len(data), p=p / total) if total > 0 else rng.integers(len(data))
        centres[i] = data[pick]
        np.minimum(distance, 1.0 - data @ centres[i], out=distance)
    return centres


def compress(features: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """[N] uint16 codes; rows that are all zero (never observed) get code 65535."""
    if len(centres) >= 65_535:
        raise ValueError(f"a uint16 codebook holds at most 65,534 centres, got {len(centres)}")
    codes = assign(features, centres).astype(np.uint16) if len(features) else np.zeros(0, np.uint16)
    codes[~_nonzero_rows(features)] = 65_535
    return codes


def decompress(codes: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """[N] codes -> [N, D] float32 features (zero rows for code 65535)."""
    padded = np.concatenate([centres.astype(np.float32), np.zeros((1, centres.shape[1]), np.float32)])
    return padded[np.minimum(codes.astype(np.int64), len(centres))]


class LiveCodebook:
    """A codebook kept across a live refiner's passes, so that a pass does not fit K centres and
    assign every Gaussian again (minutes on a map of millions). Fitted on a sample of the
    observed Gaussians at the first pass, and again (every Gaussian reassigned) whenever the
    number of observed Gaussians has doubled since the last fit: the flight has reached enough
    new ground that the centres may no longer cover its features. Between fits only the rows a
    pass recomputed are assigned, against the same centres."""

    # the fit's cost grows with the sample (20,000 rows: seconds; 100,000: minutes on two cores);
    # assigning is per Gaussian and done for the observed ones only
    def __init__(self, k: int, sample: int = 20_000, seed: int = 0):
        self.k, self.sample, self.seed = k, sample, seed
        self.centres: np.ndarray | None = None  # [K, D] float32 unit rows
        self.codes: np.ndarray | None = None  # [N] uint16, 65535 = never observed
        self.fitted_on = 0  # observed Gaussians at the last fit
        self.fits = 0

    def update(self, features: np.ndarray, observed: np.ndarray, changed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(codes [N] uint16, centres [K, D] float32) for ``features`` [N, D] (unit rows, zero
        for the unobserved) after a pass that recomputed the rows ``changed`` [N] bool."""
        count = int(observed.sum())
        if self.centres is None or self.codes is None or count >= 2 * max(self.fitted_on, 1):
            picked = np.flatnonzero(observed)
            rng = np.random.default_rng(self.seed + self.fits)
            picked = np.sort(rng.choice(picked, min(self.sample, len(picked)), replace=False))
            self.centres = fit_codebook(np.asarray(features[picked], np.float32), self.k, sample=len(picked))
            self.codes = np.full(len(features), 65_535, np.uint16)
            rows = np.flatnonzero(observed)
            self.fitted_on, self.fits = count, self.fits + 1
        else:
            rows = np.flatnonzero(changed)
        for start in range(0, len(rows), 262_144):  # the float32 copy of all the rows never exists
            chunk = rows[start : start + 262_144]
            self.codes[chunk] = compress(np.asarray(features[chunk]), self.centres)
        return self.codes, self.centres
