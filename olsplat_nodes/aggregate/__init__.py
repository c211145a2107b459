"""The method's core: per-view Gaussian observations, consistency refinement (pure, no I/O)."""

from .config import AggregationConfig
from .observe import ViewObservations, observe_view, stack_levels
from .quality import pixel_quality
from .refine import refine_observations
from .store import ObservationStore

__all__ = [
    "AggregationConfig",
    "ObservationStore",
    "ViewObservations",
    "observe_view",
    "pixel_quality",
    "refine_observations",
    "stack_levels",
]
