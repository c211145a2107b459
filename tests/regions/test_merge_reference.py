"""The compiled greedy merge against its Python oracle: the same label maps, bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from olsplat_nodes.regions import RegionConfig
from olsplat_nodes.regions._reference import merge_levels_python
from olsplat_nodes.regions.superpixel_merge import merge_levels, superpixel_graph

from .test_regions import blocks_image


def _work_image(shared_data, name: str) -> np.ndarray:
    """A real UAV photo at the size the region encoder merges a 960x720 frame at."""
    bgr = cv2.imread(str(shared_data / "caliterra" / name))
    assert bgr is not None, name
    return cv2.resize(bgr[..., ::-1], (480, 360), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("name", ["IMG_9354.jpg", "IMG_9360.jpg"])
def test_real_photos_merge_exactly_as_the_python_loop(shared_data, name):
    config = RegionConfig()
    graph = superpixel_graph(_work_image(shared_data, name), 6, (2.5, config.mean_shift[1]))
    targets = config.scaled_counts(720, 960)  # 54, 180, 540: the default levels of a 960x720 frame
    fast = merge_levels(graph, config.edge_weight, targets)
    assert np.array_equal(fast, merge_levels_python(graph, config.edge_weight, targets))
    assert [int(level.max()) + 1 for level in fast] == sorted(targets)


def test_targets_beyond_the_superpixels_and_a_single_region():
    image, _ = blocks_image(3)
    graph = superpixel_graph(image, 12, (5.0, 10.0))
    n = len(graph.sizes)
    targets = [1, 7, n - 1, n, n + 50]  # all merged, some, one merge, none, more than there are
    fast = merge_levels(graph, 3.0, targets)
    assert np.array_equal(fast, merge_levels_python(graph, 3.0, targets))
    assert [int(level.max()) + 1 for level in fast] == [1, 7, n - 1, n, n]
