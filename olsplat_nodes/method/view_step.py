"""The method's per-view step, shared by the live accumulator and the offline runs: one view's
regions and features in, its Gaussian observations appended to the store."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from ..aggregate import ObservationStore, observe_view, stack_levels
from ..aggregate.vala import observe_view_centres
from ..raster import rasterize
from ..scene import Camera, Gaussians
from .table import Method

if TYPE_CHECKING:
    from ..structure.branch import StructuralBranch


def add_view(
    gaussians: Gaussians,
    camera: Camera,
    label_maps: np.ndarray,
    bank: list[np.ndarray],
    method: Method,
    store: ObservationStore,
    branch: StructuralBranch | None = None,
) -> dict[str, float]:
    """Render the view's adaptive Top-K, fuse its bank with the 3D branch (if any), observe,
    append to ``store``.

    ``label_maps`` [L, H, W] int32 (-1 = no region), ``bank`` one [R_l, D] float32 feature
    array per level. Returns the seconds of each stage (rasterize, fuse, observe, append) and
    ``kept``, the number of Gaussians the view observed."""
    t0 = time.perf_counter()
    rendered = rasterize(gaussians, camera, method.raster)
    assert rendered.topk_ids is not None and rendered.topk_weights is not None  # rasterize always keeps Top-K
    t1 = time.perf_counter()
    if branch is not None:
        bank = branch.fuse_view(camera, rendered.depth, label_maps, bank)
    t2 = time.perf_counter()
    slots, stacked = stack_levels(label_maps, bank)
    config = method.aggregation
    if config.view_feature == "centre":  # VALA: each Gaussian's centre pixel, then its visibility gate
        observations = observe_view_centres(
            rendered.topk_ids, rendered.topk_weights, rendered.means2d, rendered.radii, slots, len(gaussians), config
        )
    else:
        observations = observe_view(rendered.topk_ids, rendered.topk_weights, slots, len(gaussians), config)
    t3 = time.perf_counter()
    store.append(camera.name, observations, stacked)
    t4 = time.perf_counter()
    return {
        "rasterize": t1 - t0,
        "fuse": t2 - t1,
        "observe": t3 - t2,
        "append": t4 - t3,
        "kept": float(len(observations)),
    }
