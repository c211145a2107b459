"""Multi-level regions of one image: L label maps, coarse to fine."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RegionLevels:
    """``label_maps[l]`` [H, W] int32 gives every pixel a region id in 0..counts[l]-1 at level l.

    Level 0 is the coarsest. Region ids are contiguous per level; -1 marks pixels that belong to
    no region (none by the default proposer, which covers the image).
    """

    label_maps: np.ndarray  # [L, H, W] int32

    def __post_init__(self) -> None:
        self.label_maps = np.ascontiguousarray(self.label_maps, dtype=np.int32)
        if self.label_maps.ndim != 3:
            raise ValueError(f"label_maps must be [L, H, W], got shape {self.label_maps.shape}")

    @property
    def n_levels(self) -> int:
        return self.label_maps.shape[0]

    @property
    def counts(self) -> list[int]:
        """Regions per level."""
        return [int(level.max()) + 1 for level in self.label_maps]


def relabel_contiguous(labels: np.ndarray) -> np.ndarray:
    """Map the ids of ``labels`` (any ints >= 0) onto 0..K-1, keeping their order; -1 stays -1."""
    valid = labels >= 0
    top = int(labels.max()) if labels.size else -1
    if top < 0:
        return np.full(labels.shape, -1, np.int32)
    if top <= 4 * labels.size:  # ids as dense as a label map's: a lookup table, no sort
        present = np.zeros(top + 2, bool)
        present[labels[valid]] = True
        lookup = (np.cumsum(present) - 1).astype(np.int32)
        lookup[-1] = -1  # index -1 (an invalid pixel) reads this entry
        return lookup[np.where(valid, labels, -1)]
    out = np.full(labels.shape, -1, np.int32)
    _, inverse = np.unique(labels[valid], return_inverse=True)
    out[valid] = inverse.reshape(-1)
    return out
