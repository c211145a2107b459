"""The method's aggregation core and its storage.

Pure functions over arrays: pixel quality, per-view observations, consistency refinement
(``_reference.py`` is the dense oracle). Storage of a run, on disk: the append-only
observation store, the language map snapshots and the run's saved views (photo + camera).
"""

from .config import AggregationConfig
from .observe import ViewObservations, observe_view, stack_levels
from .quality import pixel_quality
from .refine import refine_observations
from .snapshot import LanguageMap, latest_map, write_snapshot
from .store import ObservationStore
from .views import SavedView, load_views, save_view

__all__ = [
    "AggregationConfig",
    "LanguageMap",
    "ObservationStore",
    "SavedView",
    "ViewObservations",
    "latest_map",
    "load_views",
    "observe_view",
    "pixel_quality",
    "refine_observations",
    "save_view",
    "stack_levels",
    "write_snapshot",
]
