"""The method's core: per-view Gaussian observations, consistency refinement (pure, no I/O)."""

from .config import AggregationConfig
from .observe import ViewObservations, observe_view, stack_levels
from .quality import pixel_quality

__all__ = ["AggregationConfig", "ViewObservations", "observe_view", "pixel_quality", "stack_levels"]
