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

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit, typed, types

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


@dataclass(frozen=True)
class SuperpixelGraph:
    """A view's superpixels and their neighbourhood, what the greedy merge starts from."""

    labels: np.ndarray  # [H, W] int32 superpixel ids 0..n-1
    sizes: np.ndarray  # [n] float64 pixels
    means: np.ndarray  # [n, 3] float64 mean Lab colour (L 0..100, a/b centred on 0)
    pairs: np.ndarray  # [E, 2] int64 neighbours a < b, in increasing (a, b) order
    lengths: np.ndarray  # [E] float64 shared boundary, in pixel pairs
    grad_sums: np.ndarray  # [E] float64 Lab gradient summed along the boundary

    def first_costs(self, edge_weight: float) -> np.ndarray:
        """[E] float64 every pair's merge cost (``_cost``'s formula, vectorised: the same numbers)."""
        a, b = self.pairs[:, 0], self.pairs[:, 1]
        colour = ((self.means[a] - self.means[b]) ** 2).sum(1)
        sizes = self.sizes
        return (
            sizes[a] * sizes[b] / (sizes[a] + sizes[b]) * (colour + (edge_weight * self.grad_sums / self.lengths) ** 2)
        )


def superpixel_graph(image_rgb: np.ndarray, superpixel_px: int, mean_shift: tuple[float, float]) -> SuperpixelGraph:
    """Smooth [H, W, 3] uint8 RGB (mean shift), cut it into SLIC superpixels in Lab colour, and
    measure each one and each pair of neighbours."""
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
    return SuperpixelGraph(labels, sizes, means, *_adjacency(labels, gradient))


def merge_levels(graph: SuperpixelGraph, edge_weight: float, targets: list[int]) -> np.ndarray:
    """[L, H, W] int32 label maps, coarse to fine, with the given region counts (any order):
    neighbours merged greedily, cheapest first (``_merge``), each map taken when the count
    reaches its target."""
    n = len(graph.sizes)
    targets = sorted(targets, reverse=True)  # fine first
    reached = [t for t in targets if t >= n]  # no merge needed: the superpixels themselves
    pending = np.array([t for t in targets if t < n], np.int64)
    a, b = graph.pairs[:, 0], graph.pairs[:, 1]
    parents = _merge(
        n, a, b, graph.lengths, graph.grad_sums, graph.first_costs(edge_weight), graph.means, graph.sizes,
        edge_weight, pending,
    )  # fmt: skip
    snapshots = {t: relabel_contiguous(graph.labels) for t in reached}
    for target, parent in zip(pending.tolist(), parents, strict=True):
        snapshots[target] = relabel_contiguous(parent[graph.labels])  # parent[] always holds roots
    return np.stack([snapshots[t] for t in sorted(snapshots)])


def _merge_levels(
    image_rgb: np.ndarray, superpixel_px: int, mean_shift: tuple[float, float], edge_weight: float, targets: list[int]
) -> np.ndarray:
    """[L, H, W] int32 label maps, coarse to fine, with the given region counts (any order)."""
    return merge_levels(superpixel_graph(image_rgb, superpixel_px, mean_shift), edge_weight, targets)


@njit(cache=True)
def _cost(a, b, e, size, mean, e_length, e_grad, edge_weight):
    """The merge cost of neighbours a < b sharing boundary record e: Ward-like colour
    difference plus the boundary gradient (module docstring)."""
    colour = (mean[a, 0] - mean[b, 0]) ** 2 + (mean[a, 1] - mean[b, 1]) ** 2 + (mean[a, 2] - mean[b, 2]) ** 2
    edge = e_grad[e] / e_length[e]
    return size[a] * size[b] / (size[a] + size[b]) * (colour + (edge_weight * edge) ** 2)


@njit(cache=True)
def _before(heap, i, j):
    """Whether heap row i orders before row j: (cost, a, b, version a, version b) compared as
    Python compares tuples."""
    for c in range(5):
        if heap[i, c] != heap[j, c]:
            return heap[i, c] < heap[j, c]
    return False


@njit(cache=True)
def _swap(heap, i, j):
    for c in range(5):
        heap[i, c], heap[j, c] = heap[j, c], heap[i, c]


@njit(cache=True)
def _sift_up(heap, i):
    while i > 0:
        up = (i - 1) >> 1
        if not _before(heap, i, up):
            return
        _swap(heap, i, up)
        i = up


@njit(cache=True)
def _sift_down(heap, i, n):
    while True:
        smallest, left = i, 2 * i + 1
        if left < n and _before(heap, left, smallest):
            smallest = left
        if left + 1 < n and _before(heap, left + 1, smallest):
            smallest = left + 1
        if smallest == i:
            return
        _swap(heap, i, smallest)
        i = smallest


@njit(cache=True)
def _merge(n, pair_a, pair_b, lengths, grad_sums, first_costs, means, sizes, edge_weight, pending):
    """Greedy merging, cheapest pair first: [len(pending), n] int64 parent arrays (every
    superpixel's region root) taken when the region count reaches each target of ``pending``
    (descending, each < n; a target not reached takes the last state).

    The same float64 arithmetic in the same order as ``_reference.merge_levels_python`` (the Python
    loop it replaces; a test compares their label maps exactly): the heap holds (cost, a, b,
    version a, version b) with a < b, so ties break alike; an entry is stale once either side
    merged or changed since it was pushed."""
    size = sizes.copy()
    mean = means.copy()
    # boundary records: both neighbours' dicts hold the same record id, as the reference's
    # dicts share one [length, grad_sum] list
    e_length = np.empty(max(1, len(lengths)), np.float64)
    e_grad = np.empty(max(1, len(lengths)), np.float64)
    neighbours = typed.List()
    for _ in range(n):
        neighbours.append(typed.Dict.empty(key_type=types.int64, value_type=types.int64))
    # the heap: rows (cost, a, b, version a, version b), float64 (ids and versions are exact
    # in a float64 far beyond any image's superpixel count)
    heap = np.zeros((max(16, 4 * len(pair_a)), 5), np.float64)
    n_heap = len(pair_a)
    for e in range(n_heap):
        a, b = pair_a[e], pair_b[e]
        e_length[e], e_grad[e] = lengths[e], grad_sums[e]
        neighbours[a][b] = e
        neighbours[b][a] = e
        heap[e, 0], heap[e, 1], heap[e, 2] = first_costs[e], a, b
    for i in range(n_heap // 2 - 1, -1, -1):
        _sift_down(heap, i, n_heap)
    parent = np.arange(n)
    version = np.zeros(n, np.int64)
    out = np.empty((len(pending), n), np.int64)
    alive = n
    next_target = 0
    while n_heap > 0 and next_target < len(pending):
        a, b, va, vb = int(heap[0, 1]), int(heap[0, 2]), int(heap[0, 3]), int(heap[0, 4])
        n_heap -= 1
        _swap(heap, 0, n_heap)
        _sift_down(heap, 0, n_heap)
        if parent[a] != a or parent[b] != b or va != version[a] or vb != version[b]:
            continue
        total = size[a] + size[b]  # merge b into a
        for c in range(3):
            mean[a, c] = (mean[a, c] * size[a] + mean[b, c] * size[b]) / total
        size[a] = total
        parent[b] = a
        for i in range(n):
            if parent[i] == b:
                parent[i] = a
        del neighbours[a][b]
        del neighbours[b][a]
        for c, e in neighbours[b].items():
            del neighbours[c][b]
            if c in neighbours[a]:
                shared = neighbours[a][c]
                e_length[shared] = e_length[e] + e_length[shared]
                e_grad[shared] = e_grad[e] + e_grad[shared]
            else:
                neighbours[a][c] = e
                neighbours[c][a] = e
        neighbours[b].clear()
        version[a] += 1
        for c, e in neighbours[a].items():
            if n_heap == len(heap):  # grow by half
                grown = np.zeros((len(heap) + len(heap) // 2, 5), np.float64)
                grown[:n_heap] = heap
                heap = grown
            low, high = min(a, c), max(a, c)
            heap[n_heap, 0] = _cost(low, high, e, size, mean, e_length, e_grad, edge_weight)
            heap[n_heap, 1], heap[n_heap, 2] = low, high
            heap[n_heap, 3], heap[n_heap, 4] = version[low], version[high]
            _sift_up(heap, n_heap)
            n_heap += 1
        alive -= 1
        while next_target < len(pending) and alive <= pending[next_target]:
            out[next_target] = parent
            next_target += 1
    for t in range(next_target, len(pending)):  # fewer merges possible than asked (disconnected image?)
        out[t] = parent
    return out
