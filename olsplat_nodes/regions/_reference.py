"""The greedy region merge as a plain Python loop: the oracle of ``superpixel_merge._merge``.

Dicts of neighbours, Python floats and ``heapq``; a few tenths of a second per 480x360 view,
so only for tests (``tests/regions/test_merge_reference.py`` compares the label maps exactly).
"""

from __future__ import annotations

import heapq

import numpy as np

from .levels import relabel_contiguous
from .superpixel_merge import SuperpixelGraph


def merge_levels_python(graph: SuperpixelGraph, edge_weight: float, targets: list[int]) -> np.ndarray:
    """[L, H, W] int32 label maps, coarse to fine, with the given region counts: as
    ``superpixel_merge.merge_levels``."""
    labels, sizes, means = graph.labels, graph.sizes, graph.means
    pairs, lengths, grad_sums = graph.pairs, graph.lengths, graph.grad_sums
    n = len(sizes)
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
