"""Does a view see the prior map? Two figures per view, from the render the per-view step makes
anyway (the accumulated alpha and the per-pixel Top-K of ``raster.rasterize``): nothing is
rendered twice.

- ``coverage``: the share of the frame's pixels that the map covers, a pixel being covered when
  the accumulated alpha of the map's Gaussians there (1 - final transmittance) exceeds
  ``ALPHA_COVERED`` (0.5: more map than background).
- ``height_m``: the camera centre's height above the map's ground under the view, in map units
  (metres for a georeferenced map). The world's up axis is +z (ENU: the simulator's maps and
  the photo sources' poses). The ground is the ``GROUND_PERCENTILE`` (5th) percentile of the z
  of each covered pixel's heaviest contributor (Top-K rank 0): the low part of the surface the
  view sees, under roofs and trees, so the footprint is the view's own and not the whole map's
  (a hilly map's far side does not move it). NaN when no pixel is covered.

A view whose camera is not above the map (a wrong map, a georeference off by the ground's
altitude, a wrong camera model) typically sees some of the map at an angle or from inside it,
so both figures are checked (``CoverageGate``).

Measured with ``python -m olsplat_nodes.bench.coverage --map MAP.ply SOURCE...`` (the default
method's render; flights from ``olsplat sim make --preset tiny|small --seed 0``, photos
``../shared/data/caliterra``, exif_folder poses):

| views over a map                              | coverage min / median / max | height min / median (m) |
|-----------------------------------------------|-----------------------------|-------------------------|
| tiny flight (12) over its map                 | 0.447 / 0.749 / 0.938       | 59.5 / 60.1             |
| small flight (60) over its map                | 0.528 / 0.875 / 1.000       | 69.2 / 70.0             |
| caliterra photos (24) over the tiny map       | 0.000 / 0.023 / 1.000       | 0.0 / 11.5              |
| caliterra photos (24) over the small map      | 0.082 / 0.381 / 1.000       | 0.0 / 21.6              |

The real photos' first frames sit inside the wrong map at its ground (the photo source puts the
world origin at the first photo: heights 0.0, 1.3, 2.6, 4.3, 0.3 m over the tiny map, coverage
1.0: the camera is among the Gaussians); later ones see little of it (coverage 0.000-0.115 for
14 of 24 over the tiny map). Defaults: ``min_coverage`` 0.2, under half of the simulated flights'
worst view (0.447, a view half off the town's edge) and above most wrong views; ``min_height_m``
10 m, a sixth of the simulated flights' lowest and above the wrong photos' first five (all
under 6.1 m over either map). A real survey flown lower than 10 m over its map needs a smaller
``min_height_m``. Neither figure alone tells every wrong view (three caliterra photos over the
tiny map, at 45-49 m with 0.31-0.39 coverage, pass the gate): the run's first views are what
the accumulator judges the run by (``off_map_views``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ALPHA_COVERED = 0.5  # a pixel is covered by the map when its accumulated alpha exceeds this
GROUND_PERCENTILE = 5.0  # the ground under a view: this percentile of its covered pixels' surface z
_MAX_GROUND_SAMPLES = 1 << 16  # covered pixels sampled for the ground (an even grid), at most


@dataclass(frozen=True)
class MapCoverage:
    coverage: float  # share of the frame's pixels covered by the map, 0..1
    height_m: float  # camera centre above the map's ground under the view (map units; nan: nothing covered)

    def describe(self) -> str:
        return f"map coverage {self.coverage:.1%}, camera {self.height_m:.1f} m above the map's ground under the view"


def off_map_error(refused: list[tuple[str, MapCoverage]], gate: CoverageGate, map_path: str) -> str:
    """The one message for a run whose first views were all refused (the live accumulator's
    ERROR status and the offline run's error say the same)."""
    figures = "; ".join(f"{name}: {seen.describe()}" for name, seen in refused)
    return (
        "views do not overlap the map: wrong map, wrong georeference or wrong camera model? "
        f"The first {len(refused)} views were refused ({figures}; a view needs >= {gate.min_coverage:.0%} of its "
        f"frame covered and the camera >= {gate.min_height_m:g} m above the map's ground; map {map_path})"
    )


@dataclass(frozen=True)
class CoverageGate:
    """Which views the accumulator takes: at least ``min_coverage`` of the frame covered by the
    map, and the camera at least ``min_height_m`` above the map's ground under the view."""

    min_coverage: float = 0.2
    min_height_m: float = 10.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"min_coverage must be in [0, 1], got min_coverage={self.min_coverage}")
        if not np.isfinite(self.min_height_m):
            raise ValueError(f"min_height_m must be finite, got min_height_m={self.min_height_m}")

    def refuses(self, seen: MapCoverage) -> bool:
        """True when too little of the frame is covered, or the camera is too low over what is
        (a view that covers nothing has no height: only ``min_coverage`` judges it)."""
        return seen.coverage < self.min_coverage or bool(seen.height_m < self.min_height_m)


def _grid_step(height: int, width: int) -> int:
    """The pixel step of the even grid sampled for the ground: every pixel up to 65,536 pixels."""
    return max(1, int(np.ceil(np.sqrt(height * width / _MAX_GROUND_SAMPLES))))


def map_coverage(
    alpha: np.ndarray,  # [H, W] float32 accumulated opacity of the map's Gaussians (RenderResult.alpha)
    topk_ids: np.ndarray,  # [H, W, K] int32 Gaussian indices by weight, heaviest first, -1 padded
    means_z: np.ndarray,  # [N] the Gaussians' centre z (world, up)
    camera_z: float,  # the camera centre's z (world)
) -> MapCoverage:
    """How much of the frame the map covers and how high the camera is above the ground it
    sees (the module docstring has the rules); ``_map_coverage_reference`` is the oracle."""
    if alpha.ndim != 2 or topk_ids.shape[:2] != alpha.shape or topk_ids.ndim != 3:
        raise ValueError(f"need alpha [H, W] and topk_ids [H, W, K], got {alpha.shape} and {topk_ids.shape}")
    covered = alpha > ALPHA_COVERED
    coverage = float(covered.mean()) if covered.size else 0.0
    step = _grid_step(*alpha.shape)
    ids = topk_ids[::step, ::step, 0][covered[::step, ::step]] if topk_ids.shape[2] else np.zeros(0, np.int32)
    ids = ids[ids >= 0]
    if not len(ids):
        return MapCoverage(coverage, float("nan"))
    ground = float(np.percentile(np.asarray(means_z, np.float64)[ids], GROUND_PERCENTILE))
    return MapCoverage(coverage, float(camera_z) - ground)


def _map_coverage_reference(alpha, topk_ids, means_z, camera_z) -> MapCoverage:
    """Pixel by pixel, the rules as written: the slow oracle of ``map_coverage``."""
    height, width = alpha.shape
    step = _grid_step(height, width)
    covered = 0
    for y in range(height):
        for x in range(width):
            covered += float(alpha[y, x]) > ALPHA_COVERED
    zs = []
    for y in range(0, height, step):
        for x in range(0, width, step):
            if float(alpha[y, x]) > ALPHA_COVERED and topk_ids.shape[2] and topk_ids[y, x, 0] >= 0:
                zs.append(float(means_z[topk_ids[y, x, 0]]))
    if not zs:
        return MapCoverage(covered / (height * width), float("nan"))
    zs.sort()  # linear interpolation between the closest ranks (numpy's default percentile)
    rank = GROUND_PERCENTILE / 100.0 * (len(zs) - 1)
    low = int(np.floor(rank))
    high = min(low + 1, len(zs) - 1)
    ground = zs[low] + (zs[high] - zs[low]) * (rank - low)
    return MapCoverage(covered / (height * width), float(camera_z) - ground)
