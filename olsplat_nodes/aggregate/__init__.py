"""The method's aggregation numerics: pure functions over arrays. Pixel quality, per-view
observations, consistency refinement, VALA's baseline and the feature codebook
(``_reference.py`` is the dense oracle). The run's storage on disk is ``olsplat_nodes.storage``;
the refiner's live map over a growing store is ``method/live.py``.
"""

from .config import AggregationConfig
from .observe import ViewObservations, observe_view, stack_levels
from .quality import pixel_quality
from .refine import refine_observations

__all__ = [
    "AggregationConfig",
    "ViewObservations",
    "observe_view",
    "pixel_quality",
    "refine_observations",
    "stack_levels",
]
