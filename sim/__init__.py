"""olsplat_sim: synthetic UAV scenes and replay (the replay simulator grows here)."""

from .town import Town, make_town

__all__ = ["Town", "make_town"]
