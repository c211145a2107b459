"""The method's per-view step, shared by the live accumulator and the offline runs: one view's
regions and features in, its Gaussian observations appended to the store. A view that does not
see the prior map (``coverage.CoverageGate``) is refused right after its render, before the 3D
branch trains on it."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..aggregate import ViewObservations, observe_view, stack_levels
from ..aggregate.vala import observe_view_centres
from ..raster import RenderResult, rasterize
from ..scene import Camera, Gaussians
from ..storage import ObservationStore
from .coverage import CoverageGate, MapCoverage, map_coverage
from .table import Method

if TYPE_CHECKING:
    from ..structure.branch import StructuralBranch


class ViewOffMap(ValueError):
    """A view the coverage gate refused: its camera does not see the prior map (enough of it, or
    from above its ground). ``seen`` has the figures."""

    def __init__(self, name: str, seen: MapCoverage, gate: CoverageGate):
        self.name, self.seen, self.gate = name, seen, gate
        super().__init__(
            f"view {name!r} refused: {seen.describe()} (needs >= {gate.min_coverage:.0%} and >= "
            f"{gate.min_height_m:g} m)"
        )


@dataclass(frozen=True)
class ViewRender:
    """A view's Top-K render as the per-view step takes it: ``camera`` is the one rendered (the
    view's own, or scaled by the method's ``raster.topk_scale``), ``pixel_area`` a rendered
    pixel's area in the view's own pixels (1, or 1 / topk_scale^2)."""

    name: str  # the view's name (its camera's)
    camera: Camera
    result: RenderResult
    pixel_area: float


def render_view(gaussians: Gaussians, camera: Camera, method: Method) -> ViewRender:
    """The view's adaptive Top-K render, which depends on the map, the camera and the method's
    raster settings only (not on the view's regions): so it may be made ahead of them, on
    another thread, and come out the same. No colour (the per-view step never reads it)."""
    pixel_area = 1.0
    rendered_camera = camera
    if method.raster.topk_scale != 1.0:  # a smaller Top-K render: labels sampled at its pixels
        if method.aggregation.view_feature == "centre":
            raise ValueError(f"{method.name}: topk_scale applies to the pixel-weighted view features only")
        rendered_camera = camera.scaled(method.raster.topk_scale)
        pixel_area = camera.width * camera.height / (rendered_camera.width * rendered_camera.height)
    result = rasterize(gaussians, rendered_camera, method.raster, want_rgb=False)
    return ViewRender(camera.name, rendered_camera, result, pixel_area)


def view_observations(
    gaussians: Gaussians,
    camera: Camera,
    label_maps: np.ndarray,
    bank: list[np.ndarray],
    method: Method,
    branch: StructuralBranch | None = None,
    gate: CoverageGate | None = None,
    rendered: ViewRender | None = None,
) -> tuple[ViewObservations, np.ndarray, dict[str, float]]:
    """One view's observations, touching no store: render the view's adaptive Top-K, measure how
    much of the frame the map covers (``coverage.map_coverage``, from that render), fuse its bank
    with the 3D branch (if any), observe.

    ``label_maps`` [L, H, W] int32 (-1 = no region), ``bank`` one [R_l, D] float32 feature
    array per level. Returns the observations, the stacked region bank [sum R_l, D] they refer
    to, and the seconds of each stage (rasterize, fuse, observe) with the view's ``coverage``
    (0..1) and ``height_m`` (the camera above the map's ground under the view). Raises
    ``ViewOffMap`` when ``gate`` refuses the view (nothing fused, nothing observed). With the
    method's ``raster.topk_scale`` below 1 the render, the 3D branch and the observations work on
    the view scaled by it (``Camera.scaled``, ``sample_label_maps``), strengths counted in the
    view's own pixels. ``rendered``: this view's ``render_view``, made beforehand (the accumulator
    renders the next queued view while it observes this one); None renders it here. With it the
    "rasterize" seconds are only the coverage measure (the render was made elsewhere)."""
    t0 = time.perf_counter()
    view = render_view(gaussians, camera, method) if rendered is None else rendered
    if view.name != camera.name:
        raise ValueError(f"the render given is of view {view.name!r}, not {camera.name!r}")
    camera, render, pixel_area = view.camera, view.result, view.pixel_area
    if pixel_area != 1.0:  # a smaller Top-K render: labels sampled at its pixels
        label_maps = sample_label_maps(label_maps, camera.width, camera.height)
    rendered_ids, rendered_weights = render.topk_ids, render.topk_weights
    assert rendered_ids is not None and rendered_weights is not None  # rasterize always keeps Top-K
    seen = map_coverage(render.alpha, rendered_ids, gaussians.means[:, 2], float(camera.center[2]))
    if gate is not None and gate.refuses(seen):
        raise ViewOffMap(camera.name, seen, gate)
    t1 = time.perf_counter()
    if branch is not None:
        bank = branch.fuse_view(camera, render.depth, label_maps, bank)
    t2 = time.perf_counter()
    slots, stacked = stack_levels(label_maps, bank)
    config = method.aggregation
    if config.view_feature == "centre":  # VALA: each Gaussian's centre pixel, then its visibility gate
        observations = observe_view_centres(
            rendered_ids, rendered_weights, render.means2d, render.radii, slots, len(gaussians), config
        )
    else:
        observations = observe_view(rendered_ids, rendered_weights, slots, len(gaussians), config, pixel_area)
    t3 = time.perf_counter()
    stages = {"rasterize": t1 - t0, "fuse": t2 - t1, "observe": t3 - t2}
    return observations, stacked, {**stages, "coverage": seen.coverage, "height_m": seen.height_m}


def sample_label_maps(label_maps: np.ndarray, width: int, height: int) -> np.ndarray:
    """[L, height, width] int32: each level's region at the centres of a ``width`` x ``height``
    image of the same view (``Camera.scaled``: pixel edges map onto each other), nearest, from
    ``label_maps`` [L, H, W]. Pixel (x, y) of the small image has its centre at
    ((x + 0.5) W / width, (y + 0.5) H / height) in the large one."""
    _, full_height, full_width = label_maps.shape
    rows = np.minimum(((np.arange(height) + 0.5) * full_height / height).astype(np.int64), full_height - 1)
    columns = np.minimum(((np.arange(width) + 0.5) * full_width / width).astype(np.int64), full_width - 1)
    return np.ascontiguousarray(label_maps[:, rows[:, None], columns[None, :]], np.int32)


def add_view(
    gaussians: Gaussians,
    camera: Camera,
    label_maps: np.ndarray,
    bank: list[np.ndarray],
    method: Method,
    store: ObservationStore,
    branch: StructuralBranch | None = None,
) -> dict[str, float]:
    """``view_observations``, then append them to ``store``. Returns the seconds of each stage
    (rasterize, fuse, observe, append), ``kept``, the number of Gaussians the view observed, and
    the view's map ``coverage`` and ``height_m`` (no gate here: every view is appended)."""
    observations, stacked, stages = view_observations(gaussians, camera, label_maps, bank, method, branch)
    t0 = time.perf_counter()
    store.append(camera.name, observations, stacked)
    stages["append"] = time.perf_counter() - t0
    stages["kept"] = float(len(observations))
    return stages


# Gaussians the warm-up draws: every kernel and type of a full frame, without a full frame's
# cost (the whole 5.2M-Gaussian map in one small view took seconds of a node's start-up)
_WARM_UP_GAUSSIANS = 20_000


def warm_up(gaussians: Gaussians, method: Method, feature_dim: int = 8) -> float:
    """Run the per-view step once on a 32x24 nadir view of the map (of an even sample of at most
    20,000 of its Gaussians), so that numba compiles its kernels (or loads them from its cache)
    now and not on the first frame of a flight: on a fresh install that is ~8 s, in which a
    live camera's frames are lost. Nothing is stored. A large map's cell index for frustum
    culling (``raster/cull.py``) is made now too (0.6 s for 5.2M Gaussians). Returns the seconds
    it took."""
    from ..raster.cull import CellIndex, cells_of
    from ..raster.rasterize import _to_map_ids
    from ..scene import intrinsics, look_at

    start = time.perf_counter()
    cells_of(gaussians)
    if len(gaussians) > _WARM_UP_GAUSSIANS:  # the same kernels and types on an even sample of the map
        gaussians = gaussians.subset(np.linspace(0, len(gaussians) - 1, _WARM_UP_GAUSSIANS).astype(np.int64))
    means = np.asarray(gaussians.means, np.float64)
    low, high = np.percentile(means, [5, 95], axis=0) if len(means) else (np.zeros(3), np.ones(3))
    centre = (low + high) / 2
    height = 1.2 * float(max(high[0] - low[0], high[1] - low[1], 1.0))  # the map's bulk in view (focal 30 px)
    camera = Camera(
        "warm-up",
        32,
        24,
        intrinsics(30.0, 30.0, 16.0, 12.0),
        look_at(centre + np.array([0.0, 0.0, height]), centre, (0.0, 1.0, 0.0)),
    )
    label_maps = np.repeat(np.arange(4, dtype=np.int32), 8)[None, None, :].repeat(24, axis=1)  # 4 column regions
    bank = [np.eye(4, feature_dim, dtype=np.float32)]
    view_observations(gaussians, camera, label_maps, bank, method)
    CellIndex.build(gaussians).candidates(camera, method.raster)  # its kernels, whatever the map's size
    _to_map_ids(np.full((1, 1, 1), -1, np.int32), np.zeros(1, np.int64))  # a culled render's Top-K ids, likewise
    return time.perf_counter() - start
