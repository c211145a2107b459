"""Diagnostics of a flight and its encoders: what the evaluation world is like.

``patches``: label-free statistics of the ground seen twice, in two overlapping frames (how much
its colour, sharpness and encoder label change between them).
"""

from .patches import (
    PatchPair,
    ground_patch_pairs,
    label_of_encoder,
    patch_statistics,
    read_flight_images,
    relative_tilts_deg,
)

__all__ = [
    "PatchPair",
    "ground_patch_pairs",
    "label_of_encoder",
    "patch_statistics",
    "read_flight_images",
    "relative_tilts_deg",
]
