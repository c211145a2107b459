"""h_theta's full state survives a save and load: training continues exactly where it stopped
(what a restarted accumulator relies on)."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.structure.distill import DistillConfig, OnlineDistiller


def _views(count, rng):
    for _ in range(count):
        regions = int(rng.integers(20, 60))
        yield rng.normal(size=(regions, 7)).astype(np.float32), rng.normal(size=(regions, 5)).astype(np.float32)


def test_a_restored_distiller_continues_exactly():
    config = DistillConfig(hidden=16, steps_per_view=4, batch=32, reservoir=50, warmup_regions=10)
    views = list(_views(6, np.random.default_rng(0)))
    straight = OnlineDistiller(7, 5, config)
    for f3d, f2d in views:
        straight.update(f3d, f2d)
    first = OnlineDistiller(7, 5, config)
    for f3d, f2d in views[:3]:
        first.update(f3d, f2d)
    state = {k: np.array(v) for k, v in first.state().items()}  # as if through a file
    resumed = OnlineDistiller.from_state(state)
    assert resumed.seen == first.seen and len(resumed.memory_3d) == 50  # the reservoir is full: replay is random
    for f3d, f2d in views[3:]:
        resumed.update(f3d, f2d)
    probe = np.random.default_rng(1).normal(size=(9, 7)).astype(np.float32)
    np.testing.assert_array_equal(resumed.project(probe), straight.project(probe))
    np.testing.assert_array_equal(resumed.memory_2d, straight.memory_2d)
