"""The 3D structural branch (paper: "3D structural feature branch" and "Region-level 2D-3D
alignment and feature fusion"): reliable Gaussians as a point set, per-point structural
features, their pooling into a view's 2D regions, and the fusion with the 2D features."""

from .points import StructuralPoints, structural_points
from .pooling import Visibility, pool_regions, visible_pixels

__all__ = ["StructuralPoints", "Visibility", "pool_regions", "structural_points", "visible_pixels"]
