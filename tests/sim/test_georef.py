"""`olsplat sim make` places the town on the Earth: map/georef.json beside the map's PLY, and the
map's frame is what the georeference says (ENU metres, z up, the origin at the town's centre
on the ground)."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.scene import read_ply
from olsplat_nodes.scene.geodesy import read_georef
from olsplat_sim.labels import CATEGORY
from olsplat_sim.make import TOWN_GEOREF


def test_sim_make_writes_the_towns_georeference(tiny):
    out, summary = tiny
    georef = read_georef(out / "map" / "georef.json")
    assert georef == TOWN_GEOREF and georef.axes == "enu" and georef.height_ref == "ellipsoid"
    assert (georef.latitude, georef.longitude, georef.altitude) == (47.397742, 8.545594, 488.0)

    # the frame: metres (the map spans the preset's side), centred on the origin, ground at z = 0
    # and roofs above it (z up)
    means = read_ply(out / "map" / "point_cloud.ply").means
    category = np.load(out / "truth" / "map_labels.npz")["category"]
    side = summary["preset"]["size_m"]
    low, high = np.percentile(means[:, :2], [1, 99], axis=0)
    assert np.all(high - low > 0.8 * side) and np.all(high - low < 1.1 * side)
    assert np.abs((low + high) / 2).max() < 0.1 * side
    road, roof = (means[category == CATEGORY[name], 2] for name in ("road", "roof"))
    assert abs(np.median(road)) < 0.3 and np.median(roof) > 3.0
