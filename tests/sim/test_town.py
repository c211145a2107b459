"""The procedural town: deterministic, the size asked for, every category present and visible."""

import numpy as np

from olsplat_nodes.raster import rasterize
from olsplat_nodes.tools.demo import flight_cameras
from olsplat_sim import make_town
from olsplat_sim.town import CATEGORIES


def test_town_is_deterministic_and_sized():
    a, b = make_town(20_000, seed=3), make_town(20_000, seed=3)
    np.testing.assert_array_equal(a.gaussians.means, b.gaussians.means)
    assert abs(len(a.gaussians) - 20_000) < 500
    assert set(np.unique(a.category)) == set(range(len(CATEGORIES)))
    assert not a.gaussians.nonfinite_mask().any()
    assert not np.array_equal(make_town(20_000, seed=4).gaussians.means, a.gaussians.means)


def test_town_fills_the_nadir_view():
    town = make_town(30_000, seed=0)
    camera = flight_cameras(town.size_m, width=160, height=120)[0]
    out = rasterize(town.gaussians, camera)
    assert out.alpha.mean() > 0.95  # a UAV looking down sees ground everywhere
    assert np.median(out.depth[out.alpha > 0.5]) > 50.0  # metres: 80 m altitude minus buildings
