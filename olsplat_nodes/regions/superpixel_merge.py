"""The default region proposer: SLIC superpixels merged bottom-up into nested levels.

Aerial images are mosaics of large, fairly uniform surfaces (roofs, asphalt, lawn, crowns)
with texture inside and clear edges between. So: smooth the texture away (edge-preserving
mean shift), cut the image into ~12 px SLIC superpixels in Lab colour, then merge neighbours
greedily, cheapest first, with a Ward-like cost that weighs the colour difference by the size
of the smaller side and adds the image gradient along the shared boundary, so that merges
stop at edges (roof outline, kerb) before they cross them. The label map is saved each time
the region count reaches a level's target: levels are nested, coarse ones are unions of
finer ones.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import cv2
import numpy as np

from .levels import RegionLevels, relabel_contiguous


@dataclass(frozen=True)
class RegionConfig:
    level_counts: tuple[int, ...] = (24, 80, 240)  # regions per level at 640x480, coarse to fine
    superpixel_px: int = 12  # SLIC region size in pixels
    mean_shift: tuple[float, float] = (5.0, 10.0)  # spatial and colour radius of the pre-smoothing
    edge_weight: float = 3.0  # weight of the boundary gradient against the colour difference
    # Work on the image resized by this factor (superpixel size and smoothing radius scaled with
    # it, region counts not) and upsample the label maps (nearest): ~1/work_scale^2 cheaper,
    # region edges on a 1/work_scale pixel grid. 0.5 cuts the region step to about a third with
    # no loss of accuracy on held-out seeds (docs/decisions.md, `olsplat bench regions`).
    work_scale: float = 0.5

    def __post_init__(self) -> None:
        counts = self.level_counts
        if not counts or any(c <= 0 for c in counts) or list(counts) != sorted(counts):
            raise ValueError(f"level_counts must be positive and increasing (coarse to fine), got {counts}")
        if not 0.1 <= self.work_scale <= 1.0:
            raise ValueError(f"work_scale must be in [0.1, 1], got {self.work_scale}")

    def scaled_counts(self, height: int, width: int) -> list[int]:
        """The level targets for an image of this size (region size stays the same in pixels)."""
        scale = height * width / (640 * 480)
        return [max(1, int(round(c * scale))) for c in self.level_counts]


def _superpixels(lab: np.ndarray, size: int) -> np.ndarray:
    slic = cv2.ximgproc.createSuperpixelSLIC(lab, algorithm=cv2.ximgproc.SLICO, region_size=size, ruler=10.0)
    slic.iterate(10)
    slic.enforceLabelConnectivity(25)
    return relabel_contiguous(slic.getLabels())


def _adjacency(labels: np.ndarray, gradient: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Neighbouring superpixels: (pairs [E, 2] with a < b, boundary length [E] in pixel pairs,
    summed gradient along the boundary [E]), pairs in increasing (a, b) order."""
    n = int(labels.max()) + 1
    keys, grads = [], []
    for a, b, g in (
        (labels[:, :-1], labels[:, 1:], 0.5 * (gradient[:, :-1] + gradient[:, 1:])),
        (labels[:-1, :], labels[1:, :], 0.5 * (gradient[:-1, :] + gradient[1:, :])),
    ):
        cut = a != b
        low, high = np.minimum(a[cut], b[cut]).astype(np.int64), np.maximum(a[cut], b[cut]).astype(np.int64)
        keys.append(low * n + high)
        grads.append(g[cut])
    unique, inverse, lengths = np.unique(np.concatenate(keys), return_inverse=True, return_counts=True)
    sums = np.bincount(inverse.ravel(), weights=np.concatenate(grads), minlength=len(unique))
    return np.stack([unique // n, unique % n], 1), lengths.astype(np.float64), sums


def propose_regions(image_rgb: np.ndarray, config: RegionConfig = RegionConfig()) -> RegionLevels:
    """[H, W, 3] uint8 RGB -> nested RegionLevels, coarse to fine (see the module docstring)."""
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
        raise ValueError(f"image must be [H, W, 3] uint8 RGB, got shape {image_rgb.shape} dtype {image_rgb.dtype}")
    height, width = image_rgb.shape[:2]
    targets = config.scaled_counts(height, width)
    scale = config.work_scale
    if scale == 1.0:
        return RegionLevels(
            _merge_levels(image_rgb, config.superpixel_px, config.mean_shift, config.edge_weight, targets)
        )
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    small = cv2.resize(image_rgb, size, interpolation=cv2.INTER_AREA)
    superpixel_px = max(3, round(config.superpixel_px * scale))
    mean_shift = (config.mean_shift[0] * scale, config.mean_shift[1])  # spatial radius in pixels; colour as is
    levels = _merge_levels(small, superpixel_px, mean_shift, config.edge_weight, targets)
    full = [cv2.resize(level, (width, height), interpolation=cv2.INTER_NEAREST) for level in levels]
    return RegionLevels(np.stack([relabel_contiguous(level) for level in full]))


def _merge_levels(
    image_rgb: np.ndarray, superpixel_px: int, mean_shift: tuple[float, float], edge_weight: float, targets: list[int]
) -> np.ndarray:
    """[L, H, W] int32 label maps, coarse to fine, with the given region counts (any order)."""
    bgr = np.ascontiguousarray(image_rgb[..., ::-1])
    smooth = cv2.pyrMeanShiftFiltering(bgr, *mean_shift)
    lab_u8 = cv2.cvtColor(smooth, cv2.COLOR_BGR2Lab)
    lab = lab_u8.astype(np.float64)
    lab[..., 0] *= 100.0 / 255.0  # OpenCV 8-bit Lab: L in 0..255, a/b offset by 128
    lab[..., 1:] -= 128.0
    gx = cv2.Sobel(lab, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(lab, cv2.CV_64F, 0, 1, ksize=3)
    gradient = np.sqrt((gx**2 + gy**2).sum(-1)) / 8.0  # Lab units per pixel

    labels = _superpixels(lab_u8, superpixel_px)
    n = int(labels.max()) + 1
    sizes = np.bincount(labels.ravel(), minlength=n).astype(np.float64)
    means = (
        np.stack([np.bincount(labels.ravel(), weights=lab[..., c].ravel(), minlength=n) for c in range(3)], 1)
        / sizes[:, None]
    )
    pairs, lengths, grad_sums = _adjacency(labels, gradient)
    neighbours: list[dict[int, list[float]]] = [dict() for _ in range(n)]
    for (a, b), length, grad_sum in zip(pairs.tolist(), lengths.tolist(), grad_sums.tolist(), strict=True):
        neighbours[a][b] = neighbours[b][a] = [length, grad_sum]

    # the merge loop runs on Python floats: tens of thousands of 3-vector operations, where
    # numpy's per-call overhead would dominate (same float64 arithmetic, same order)
    mean_of: list[list[float]] = means.tolist()
    size_of: list[float] = sizes.tolist()

    def cost(a: int, b: int) -> float:
        length, grad_sum = neighbours[a][b]
        (l1, a1, b1), (l2, a2, b2) = mean_of[a], mean_of[b]
        colour = (l1 - l2) ** 2 + (a1 - a2) ** 2 + (b1 - b2) ** 2
        edge = grad_sum / length
        return size_of[a] * size_of[b] / (size_of[a] + size_of[b]) * (colour + (edge_weight * edge) ** 2)

    parent = np.arange(n)
    version = np.zeros(n, np.int64)
    # the first costs for all pairs at once (the same formula as cost(), vectorised)
    a, b = pairs[:, 0], pairs[:, 1]
    colour = ((means[a] - means[b]) ** 2).sum(1)
    first_costs = sizes[a] * sizes[b] / (sizes[a] + sizes[b]) * (colour + (edge_weight * grad_sums / lengths) ** 2)
    heap = [(c, x, y, 0, 0) for c, x, y in zip(first_costs.tolist(), a.tolist(), b.tolist(), strict=True)]
    heapq.heapify(heap)
    targets = sorted(targets, reverse=True)  # fine first
    snapshots: dict[int, np.ndarray] = {}
    alive = n

    def snapshot(target: int) -> None:
        snapshots[target] = relabel_contiguous(parent[labels])  # parent[] always holds roots

    for target in [t for t in targets if t >= alive]:
        snapshot(target)
    pending = [t for t in targets if t < alive]
    while heap and pending:
        _, a, b, va, vb = heapq.heappop(heap)
        if parent[a] != a or parent[b] != b or va != version[a] or vb != version[b]:
            continue  # stale entry: one side merged or changed since it was pushed
        # merge b into a
        total = size_of[a] + size_of[b]
        mean_of[a] = [(x * size_of[a] + y * size_of[b]) / total for x, y in zip(mean_of[a], mean_of[b], strict=True)]
        size_of[a] = total
        parent[b] = a
        parent[parent == b] = a
        del neighbours[a][b], neighbours[b][a]
        for c, (length, grad_sum) in neighbours[b].items():
            del neighbours[c][b]
            merged = neighbours[a].get(c)
            stats = [length + merged[0], grad_sum + merged[1]] if merged else [length, grad_sum]
            neighbours[a][c] = neighbours[c][a] = stats
        neighbours[b] = {}
        version[a] += 1
        for c in neighbours[a]:
            heapq.heappush(
                heap,
                (cost(a, c), a, c, version[a], version[c]) if a < c else (cost(c, a), c, a, version[c], version[a]),
            )
        alive -= 1
        while pending and alive <= pending[0]:
            snapshot(pending.pop(0))
    for target in pending:  # fewer merges possible than asked (disconnected image?)
        snapshot(target)
    return np.stack([snapshots[t] for t in sorted(snapshots)])
