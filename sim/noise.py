"""Smooth procedural noise (value noise, summed over octaves) for textures.

Pure numpy and deterministic: the lattice values come from a generator seeded by the caller.
"""

from __future__ import annotations

import numpy as np

_PERIOD = 256  # lattice cells before the pattern repeats (256 x the scale: far beyond a scene)


class Noise2D:
    """fbm(points) in about [-1, 1]; ``scale`` is the size of the largest feature in metres."""

    def __init__(self, seed: int, octaves: int = 4):
        rng = np.random.default_rng(seed)
        self.lattices = [rng.uniform(-1.0, 1.0, (_PERIOD, _PERIOD)) for _ in range(octaves)]

    def __call__(self, points: np.ndarray, scale: float) -> np.ndarray:
        """points [M, 2] metres -> [M] float64."""
        total = np.zeros(len(points))
        amplitude, norm = 1.0, 0.0
        for octave, lattice in enumerate(self.lattices):
            uv = points / (scale / 2**octave) + 17.31 * octave  # shift octaves apart
            cell = np.floor(uv).astype(np.int64)
            frac = uv - cell
            frac = frac * frac * (3.0 - 2.0 * frac)  # smoothstep: no lattice creases
            i0, j0 = cell[:, 0] % _PERIOD, cell[:, 1] % _PERIOD
            i1, j1 = (i0 + 1) % _PERIOD, (j0 + 1) % _PERIOD
            low = lattice[i0, j0] * (1 - frac[:, 0]) + lattice[i1, j0] * frac[:, 0]
            high = lattice[i0, j1] * (1 - frac[:, 0]) + lattice[i1, j1] * frac[:, 0]
            total += amplitude * (low * (1 - frac[:, 1]) + high * frac[:, 1])
            norm += amplitude
            amplitude *= 0.5
        return total / norm * 1.6  # value noise rarely reaches its bounds: stretch to about +-1
