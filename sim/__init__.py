"""olsplat_sim: synthetic UAV scenes with ground truth, flights, annotations and replay logs."""

from .labels import CATEGORIES, LABELS, QUERIES
from .scene import TruthScene, generate_scene

__all__ = ["CATEGORIES", "LABELS", "QUERIES", "TruthScene", "generate_scene"]
