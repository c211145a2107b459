"""A run's durable storage, on disk: the append-only observation store (``store``), the
language map snapshots and the map folder's versions (``snapshot``), the saved views (photo +
camera, ``views``), the store split by ground tile (``tiles``) and the record of the prior map
a run was made over (``prior``). Every write is atomic and fsynced (``durable.py``): a crash
or a power cut never leaves half a view or half a map, and an accepted view is never lost.

The method's numerics (``aggregate``) sit below this layer: the store refines its own
observations with them, and nothing here touches a socket.
"""

from .snapshot import LanguageMap, latest_map, map_history, write_snapshot
from .store import ObservationStore
from .views import SavedView, load_views, save_view

__all__ = [
    "LanguageMap",
    "ObservationStore",
    "SavedView",
    "latest_map",
    "load_views",
    "map_history",
    "save_view",
    "write_snapshot",
]
