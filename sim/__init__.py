"""olsplat_sim: synthetic UAV scenes with ground truth, flights, annotations and replay logs."""

from .labels import CATEGORIES, LABELS, QUERIES

__all__ = ["CATEGORIES", "LABELS", "QUERIES", "TruthScene", "generate_scene"]


def __getattr__(name: str):
    # the scene generator pulls in numba and OpenCV (~0.2 s): only when asked for, so that
    # `olsplat --help` and the command-line parser stay fast
    if name in ("TruthScene", "generate_scene"):
        from . import scene

        return getattr(scene, name)
    raise AttributeError(f"module 'olsplat_sim' has no attribute {name!r}")
