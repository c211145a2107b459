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

    def __post_init__(self) -> None:
        counts = self.level_counts
        if not counts or any(c <= 0 for c in counts) or list(counts) != sorted(counts):
            raise ValueError(f"level_counts must be positive and increasing (coarse to fine), got {counts}")

    def scaled_counts(self, height: int, width: int) -> list[int]:
        """The level targets for an image of this size (region size stays the same in pixels)."""
        scale = height * width / (640 * 480)
        return [max(1, int(round(c * scale))) for c in self.level_counts]


def _superpixels(lab: np.ndarray, size: int) -> np.ndarray:
    slic = cv2.ximgproc.createSuperpixelSLIC(lab, algorithm=cv2.ximgproc.SLICO, region_size=size, ruler=10.0)
    slic.iterate(10)
    slic.enforceLabelConnectivity(25)
    return relabel_contiguous(slic.getLabels())


def _adjacency(labels: np.ndarray, gradient: np.ndarray) -> dict[tuple[int, int], list[float]]:
    """(a, b) with a < b -> [boundary length in pixel pairs, summed gradient along it]."""
    pairs, grads = [], []
    for a, b, g in (
        (labels[:, :-1], labels[:, 1:], 0.5 * (gradient[:, :-1] + gradient[:, 1:])),
        (labels[:-1, :], labels[1:, :], 0.5 * (gradient[:-1, :] + gradient[1:, :])),
    ):
        cut = a != b
        pairs.append(np.stack([np.minimum(a[cut], b[cut]), np.maximum(a[cut], b[cut])], 1))
        grads.append(g[cut])
    all_pairs, all_grads = np.concatenate(pairs), np.concatenate(grads)
    keys, inverse, lengths = np.unique(all_pairs, axis=0, return_inverse=True, return_counts=True)
    sums = np.bincount(inverse.ravel(), weights=all_grads, minlength=len(keys))
    return {(int(a), int(b)): [float(n), float(s)] for (a, b), n, s in zip(keys, lengths, sums, strict=True)}


def propose_regions(image_rgb: np.ndarray, config: RegionConfig = RegionConfig()) -> RegionLevels:
    """[H, W, 3] uint8 RGB -> nested RegionLevels, coarse to fine (see the module docstring)."""
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
        raise ValueError(f"image must be [H, W, 3] uint8 RGB, got shape {image_rgb.shape} dtype {image_rgb.dtype}")
    height, width = image_rgb.shape[:2]
    bgr = np.ascontiguousarray(image_rgb[..., ::-1])
    smooth = cv2.pyrMeanShiftFiltering(bgr, *config.mean_shift)
    lab_u8 = cv2.cvtColor(smooth, cv2.COLOR_BGR2Lab)
    lab = lab_u8.astype(np.float64)
    lab[..., 0] *= 100.0 / 255.0  # OpenCV 8-bit Lab: L in 0..255, a/b offset by 128
    lab[..., 1:] -= 128.0
    gx = cv2.Sobel(lab, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(lab, cv2.CV_64F, 0, 1, ksize=3)
    gradient = np.sqrt((gx**2 + gy**2).sum(-1)) / 8.0  # Lab units per pixel

    labels = _superpixels(lab_u8, config.superpixel_px)
    n = int(labels.max()) + 1
    sizes = np.bincount(labels.ravel(), minlength=n).astype(np.float64)
    means = (
        np.stack([np.bincount(labels.ravel(), weights=lab[..., c].ravel(), minlength=n) for c in range(3)], 1)
        / sizes[:, None]
    )
    edges = _adjacency(labels, gradient)
    neighbours: list[dict[int, list[float]]] = [dict() for _ in range(n)]
    for (a, b), stats in edges.items():
        neighbours[a][b] = stats
        neighbours[b][a] = stats

    def cost(a: int, b: int) -> float:
        length, grad_sum = neighbours[a][b]
        colour = float(((means[a] - means[b]) ** 2).sum())
        edge = grad_sum / length
        return sizes[a] * sizes[b] / (sizes[a] + sizes[b]) * (colour + (config.edge_weight * edge) ** 2)

    parent = np.arange(n)
    version = np.zeros(n, np.int64)
    heap = [(cost(a, b), a, b, 0, 0) for (a, b) in edges]
    heapq.heapify(heap)
    targets = sorted(config.scaled_counts(height, width), reverse=True)  # fine first
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
        total = sizes[a] + sizes[b]
        means[a] = (means[a] * sizes[a] + means[b] * sizes[b]) / total
        sizes[a] = total
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
    return RegionLevels(np.stack([snapshots[t] for t in sorted(snapshots)]))
