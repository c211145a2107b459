"""Offline end-to-end runs of the method on scene folders (the nodes run the same core live)."""

from .offline import METHODS, Scene, aggregate_scene

__all__ = ["METHODS", "Scene", "aggregate_scene"]
