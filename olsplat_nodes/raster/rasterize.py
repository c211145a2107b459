"""The public rasterizer: one camera, one map, every output the method needs."""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit, prange

from ..scene import Camera, Gaussians
from . import heatmap_native, topk_native
from .arguments import Canvas, Outputs, Splats, TileLists, TopK
from .binning import bin_tiles
from .composite import composite_tiles
from .config import RasterConfig
from .project import Projected, project


@dataclass
class RenderResult:
    rgb: np.ndarray  # [H, W, 3] float32, 0..1 (+ background * final transmittance); [0, 0, 3] when not asked for
    alpha: np.ndarray  # [H, W] float32 accumulated opacity = sum of weights = 1 - T_final
    depth: np.ndarray  # [H, W] float32 expected camera z = sum(w z) / alpha; 0 where alpha = 0
    features: np.ndarray | None  # [H, W, D] float32 sum(w f) / (alpha + eps), when features were given
    # (with feature_queries: [H, W, Q] the cosine of that feature with each query)
    topk_ids: np.ndarray | None  # [H, W, topk_max] int32 Gaussian indices by weight, -1 padded
    topk_weights: np.ndarray | None  # [H, W, topk_max] float32 alpha*T weights, 0 padded
    projected: Projected  # the Gaussians on screen (a culled map's candidates only: see means2d, radii)
    n_gaussians: int  # N, the map's
    n_evaluations: int  # Gaussian-pixel pairs evaluated (the sigma computed)
    n_tile_pairs: int  # pairs a per-pixel loop over the tile lists (gsplat's loop) evaluates for the same image
    n_intersections: int  # Gaussian-tile pairs after binning
    n_visible: int  # Gaussians that survived projection
    seconds: dict[str, float]  # wall time per stage: project, bin, composite

    @cached_property
    def _aligned(self) -> Projected:
        return self.projected.aligned(self.n_gaussians)  # made when asked for: most callers never do

    @property
    def means2d(self) -> np.ndarray:
        """[N, 2] float32 projected centres (u, v) in pixels, pixel centres at +0.5; 0 if culled."""
        return self._aligned.means2d

    @property
    def radii(self) -> np.ndarray:
        """[N] int32 screen radius in pixels; 0 = culled (never rasterized)."""
        return self._aligned.radii


def rasterize(
    gaussians: Gaussians,
    camera: Camera,
    config: RasterConfig | None = None,
    features: np.ndarray | None = None,  # [N, D] per-Gaussian features to render (float32; float16 see below)
    want_topk: bool = True,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    feature_queries: np.ndarray | None = None,  # [Q, D] unit rows: render cos(F(p), row) instead of F(p)
    unit_features_out: np.ndarray | None = None,  # [H * W, D] float32, with feature_queries: receives F / |F|
    feature_rows: np.ndarray | None = None,  # [N] int: Gaussian g's feature is features[feature_rows[g]] (-1: 0)
    active: np.ndarray | None = None,  # [N] bool: only these are drawn (the others as if culled)
    want_rgb: bool = True,  # False: rgb empty [0, 0, 3] (the C Top-K kernel then skips the colour sums)
) -> RenderResult:
    """Render ``gaussians`` into ``camera``'s ideal pinhole image (distortion not applied).

    See ``project`` for the projection conventions and ``composite`` for the compositing and
    Top-K rules; ``_reference.rasterize_reference`` is the slow oracle with the same contract.
    With ``feature_rows`` the features are a table (e.g. a codebook's centres [K, D]) and
    Gaussian g renders row ``feature_rows[g]`` (nothing where it is -1), without the [N, D] rows.
    With ``feature_queries`` the result's ``features`` are [H, W, Q] cosine heatmaps of the
    rendered features (0 where nothing was rendered), computed per pixel in the compositing
    kernel: the [H, W, D] feature image is never made, unless ``unit_features_out`` is given:
    then that caller's buffer (C-contiguous float32 [H * W, D], e.g. one reused view after view)
    also receives each pixel's unit feature F / |F| (rows of 0 where nothing was rendered).
    Heatmaps (``feature_queries`` without Top-K) are composited by the C kernel when it is built
    (``heatmap_native.py``: same outputs, alpha within 2e-6 and cosines within 2e-5 of the numba
    kernel's). That kernel reads float16 features as they are (a language map's stored form: half
    the bytes); every other path widens them to float32 first (the same values, exactly).
    With ``active`` only the Gaussians where it is True are drawn, as if the others were not in
    the map.
    Renders without features (the accumulator's Top-K) go to the C Top-K kernel when it is built
    (``topk_native.py``: weights within a few ulp of the numba kernel's, the same ranking rule);
    with ``want_rgb`` False it leaves the colour out (every other output the same).
    """
    config = config or RasterConfig()
    n = len(gaussians)
    rows = np.zeros(0, np.int32)
    if features is None:
        feats = np.zeros((n, 0), np.float32)
    else:
        keep_half = getattr(features, "dtype", None) == np.float16 and feature_queries is not None and not want_topk
        keep_half = keep_half and heatmap_native.available(config.tile_size)  # the C kernel reads float16
        feats = np.ascontiguousarray(features, dtype=np.float16 if keep_half else np.float32)  # no copy if it is
        if feats.ndim != 2 or (feature_rows is None and feats.shape[0] != n):
            raise ValueError(f"features must be [N={n}, D], got shape {feats.shape}")
        if feature_rows is not None:
            rows = np.ascontiguousarray(feature_rows, dtype=np.int32)
            if rows.shape != (n,) or (n and (rows.min() < -1 or rows.max() >= len(feats))):
                raise ValueError(f"feature_rows must be [N={n}] rows of features [{len(feats)}, D] or -1")
    queries = np.zeros((0, feats.shape[1]), np.float32)
    if feature_queries is not None:
        queries = np.ascontiguousarray(feature_queries, dtype=np.float32)
        if features is None or queries.ndim != 2 or queries.shape[1] != feats.shape[1] or not len(queries):
            raise ValueError(f"feature_queries must be [Q >= 1, D={feats.shape[1]}] with features, got {queries.shape}")
    width, height, tile = camera.width, camera.height, config.tile_size
    unit = np.zeros((0, feats.shape[1]), np.float32)
    if unit_features_out is not None:
        shape = (height * width, feats.shape[1])
        if feature_queries is None or unit_features_out.shape != shape or unit_features_out.dtype != np.float32:
            raise ValueError(f"unit_features_out must be float32 {shape} with feature_queries")
        if not unit_features_out.flags.c_contiguous:
            raise ValueError("unit_features_out must be C-contiguous")
        unit = unit_features_out
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    clock = [time.perf_counter()]
    projected: Projected = project(gaussians, camera, config, active)
    if projected.ids is not None and features is not None:  # rows of the candidates only: their features by id
        rows = rows[projected.ids] if len(rows) else projected.ids.astype(np.int32)
    clock.append(time.perf_counter())
    order, offsets, slots = bin_tiles(projected.depths, projected.radii, projected.tile_rects, tiles_x, tiles_y)
    clock.append(time.perf_counter())

    k = config.topk_max if want_topk else 0
    native_topk = features is None and topk_native.available(tile, k)
    rgb = np.empty((height, width, 3) if want_rgb or not native_topk else (0, 0, 3), np.float32)
    alpha = np.empty((height, width), np.float32)
    depth = np.empty((height, width), np.float32)
    out_features = np.empty((height, width, len(queries) or feats.shape[1]), np.float32)
    topk_ids = np.empty((height, width, k), np.int32)  # every slot written by the kernel
    topk_weights = np.empty((height, width, k), np.float32)
    evals = np.zeros((tiles_x * tiles_y, 2), np.int64)
    # Heavy tiles cluster (buildings, horizon); a fixed shuffle spreads them over the threads.
    tile_order = np.random.default_rng(0).permutation(tiles_x * tiles_y).astype(np.int64)
    splats = Splats(projected.records, feats, rows)
    lists = TileLists(order, offsets, slots, tile_order)
    canvas = Canvas(
        width,
        height,
        tile,
        config.alpha_min,
        config.alpha_max,
        config.transmittance_min,
        config.feature_eps,
        np.asarray(background, np.float32),
        queries,
    )
    topk = TopK(k, config.topk_min, config.topk_coverage)
    out = Outputs(rgb, alpha, depth, out_features, topk_ids, topk_weights, evals, unit)
    if len(queries) and not want_topk and heatmap_native.available(tile):  # heatmaps: the C kernel, same outputs
        heatmap_native.composite_heatmaps(splats, lists, canvas, out)
    elif native_topk:  # the accumulator's render: the C kernel, same Top-K, the map's ids written at once
        topk_native.composite_topk(splats, lists, canvas, topk, out, projected.ids if want_topk else None)
    else:
        composite_tiles(splats, lists, canvas, topk, out)
        if want_topk and projected.ids is not None:
            _to_map_ids(topk_ids, projected.ids)
    clock.append(time.perf_counter())
    return RenderResult(
        rgb=rgb if want_rgb else np.zeros((0, 0, 3), np.float32),
        alpha=alpha,
        depth=depth,
        features=out_features if features is not None else None,
        topk_ids=topk_ids if want_topk else None,
        topk_weights=topk_weights if want_topk else None,
        projected=projected,
        n_gaussians=n,
        n_evaluations=int(evals[:, 0].sum()),
        n_tile_pairs=int(evals[:, 1].sum()),
        n_intersections=len(slots),
        n_visible=int((projected.radii > 0).sum()),
        seconds=dict(zip(("project", "bin", "composite"), np.diff(clock).tolist(), strict=True)),
    )


@njit(parallel=True, cache=True, nogil=True)
def _to_map_ids(topk_ids: np.ndarray, ids: np.ndarray) -> None:
    """In place: Top-K entries that are rows of a culled projection become the Gaussians' own
    indices, ids [M] int64; -1 (no entry) stays."""
    flat = topk_ids.reshape(-1)
    for e in prange(flat.shape[0]):
        if flat[e] >= 0:
            flat[e] = ids[flat[e]]
