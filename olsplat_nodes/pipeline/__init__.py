"""Offline runs of the method on scene folders (``olsplat aggregate`` / ``eval`` and the
benchmarks); the live nodes run the same per-view step (``olsplat_nodes.method``)."""

from .offline import aggregate_scene
from .scene_folder import Scene, view_features

__all__ = ["Scene", "aggregate_scene", "view_features"]
