"""The method as a whole, over the core packages (raster, aggregate, structure): the methods by
name, their typed tunable parameters, the per-view step that the live accumulator and the
offline runs share, and the store manifest that pins a run's settings."""

from .manifest import StoreManifest, check_store, claim_store, read_manifest, write_manifest
from .params import MethodParams, method_params_of
from .table import METHODS, Method, named_method
from .view_step import add_view, view_observations, warm_up

__all__ = [
    "METHODS",
    "Method",
    "MethodParams",
    "StoreManifest",
    "add_view",
    "check_store",
    "claim_store",
    "method_params_of",
    "named_method",
    "read_manifest",
    "view_observations",
    "warm_up",
    "write_manifest",
]
