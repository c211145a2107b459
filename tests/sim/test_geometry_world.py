"""World setting ``geometry.strength`` (issue 43 part 4): at strength 1 roof colours follow the
building's type and size, pavements stand behind kerbs, lawns are rough and roads smooth, and
crowns are taller; at strength 0 the town is exactly the one of before (test_world.py's digests
check the files of ``sim make``; here the arrays)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from olsplat_nodes.cli import main
from olsplat_sim.geometry import KERB_M, roof_type, tie_roof_colors
from olsplat_sim.labels import CATEGORY, LABEL, ROOF_COLORS, building_label
from olsplat_sim.layout import generate_layout
from olsplat_sim.presets import PRESETS
from olsplat_sim.scene import TruthScene, generate_scene
from olsplat_sim.world import GEOMETRY_WORLD_KEY, V1, V2, GeometryWorld, with_settings, world_keys

TINY = PRESETS["tiny"]
GROUND = ("road", "lawn", "parking", "pavement", "bare ground")


def _town(strength: float | None, seed: int = 0) -> TruthScene:
    geometry = None if strength is None else GeometryWorld(strength)
    return generate_scene(TINY.n_gaussians, TINY.size_m, seed, geometry)


@pytest.fixture(scope="module")
def towns() -> dict[float, TruthScene]:
    return {s: _town(s) for s in (0.0, 1.0)}


def _z(town: TruthScene, category: str) -> np.ndarray:
    return town.gaussians.means[town.category == CATEGORY[category], 2]


def test_strength_zero_is_the_town_of_before(towns):
    before = _town(None)
    for a, b in ((before.gaussians.means, towns[0.0].gaussians.means), (before.label, towns[0.0].label)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(before.gaussians.sh, towns[0.0].gaussians.sh)


def test_strength_one_changes_only_geometry_and_roof_labels(towns):
    old, new = towns[0.0], towns[1.0]
    n = len(old.gaussians)
    assert len(new.gaussians) > n  # the kerb faces, appended
    assert (new.category[n:] == CATEGORY["pavement"]).all() and (new.label[n:] == LABEL["pavement"]).all()
    same = np.isin(old.category, [CATEGORY[c] for c in ("road", "parking", "bare ground", "wall", "roof", "car")])
    np.testing.assert_array_equal(new.gaussians.means[:n][same], old.gaussians.means[same])
    np.testing.assert_array_equal(new.gaussians.log_scales[:n], old.gaussians.log_scales)  # paired draws
    np.testing.assert_array_equal(new.instance[:n], old.instance)
    # a building's Gaussians carry its (possibly tied) roof colour's label
    for b in new.layout.buildings:
        assert (new.label[new.instance == b.instance] == LABEL[building_label(b.roof_color)]).all()


def _tied_share(strength: float, seeds=range(40)) -> dict[str, float]:
    """Share of roofs with the colours their type is tied to, pooled over 130 m layouts."""
    tied = {"large flat": ("grey", "white"), "gable": ("red",), "small flat": ("white", "blue")}
    hits: dict[str, list[bool]] = {k: [] for k in tied}
    for seed in seeds:
        layout = generate_layout(130.0, np.random.default_rng(seed))
        if strength > 0:  # as generate_scene does
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=GEOMETRY_WORLD_KEY))
            tie_roof_colors(layout, strength, rng)
        for b in layout.buildings:
            kind = roof_type(b.boxes, b.roof)
            hits[kind].append(b.roof_color in tied[kind])
    assert all(len(v) >= 20 for v in hits.values()), {k: len(v) for k, v in hits.items()}
    return {k: float(np.mean(v)) for k, v in hits.items()}


def test_large_flat_roofs_take_their_tied_colours():
    zero, half, one = _tied_share(0.0), _tied_share(0.5), _tied_share(1.0)
    assert one["large flat"] == 1.0 and zero["large flat"] < 0.6, (zero, one)
    assert one["gable"] > zero["gable"] + 0.15 and one["small flat"] > zero["small flat"] + 0.15, (zero, one)
    assert zero["large flat"] < half["large flat"] < one["large flat"]  # the strength is a dial


def test_every_colour_is_still_common_at_strength_one():
    layouts = [generate_layout(130.0, np.random.default_rng(seed)) for seed in range(20)]
    for seed, layout in enumerate(layouts):
        tie_roof_colors(layout, 1.0, np.random.default_rng(np.random.SeedSequence(seed, spawn_key=GEOMETRY_WORLD_KEY)))
    colours = [b.roof_color for layout in layouts for b in layout.buildings]
    shares = {c: colours.count(c) / len(colours) for c in ROOF_COLORS}
    assert min(shares.values()) > 0.1, shares


def _near_road_edge(town: TruthScene, xy: np.ndarray, within: float) -> np.ndarray:
    """[M] bool: within ``within`` metres outside a road's edge line."""
    near = np.zeros(len(xy), bool)
    for axis, centre, half_width in town.layout.roads:
        across = xy[:, 1] if axis == "x" else xy[:, 0]
        off = np.abs(across - centre) - half_width
        near |= (off > -0.05) & (off < within)
    return near


def test_kerbs_stand_above_the_road_along_its_edges(towns):
    for strength, town in towns.items():
        means = town.gaussians.means
        pavement = town.category == CATEGORY["pavement"]
        edge = pavement & _near_road_edge(town, means[:, :2], 1.0)
        assert edge.sum() > 100
        raised = np.mean(means[edge, 2] > 0.3 * KERB_M)
        if strength == 0.0:
            assert raised < 0.02, raised
        else:
            assert raised > 0.9, raised  # pavement tops and kerb faces (all but their lowest 30 %)
            road = town.category == CATEGORY["road"]
            assert np.abs(np.median(means[road, 2])) < 0.005
    # the kerb faces (appended last) stand on the road edges (or a parking lot's), 0..KERB_M high
    town, n = towns[1.0], len(towns[0.0].gaussians)
    faces = town.gaussians.means[n:]
    assert len(faces) > 20
    assert faces[:, 2].min() > -0.05 and faces[:, 2].max() < KERB_M + 0.05
    assert np.mean(_near_road_edge(town, faces[:, :2], 0.3)) > 0.5


def test_lawns_are_rough_and_roads_smooth(towns):
    spread = {s: {c: float(np.std(_z(t, c))) for c in ("lawn", "road", "parking")} for s, t in towns.items()}
    assert spread[1.0]["lawn"] > 2.0 * max(spread[1.0]["road"], spread[1.0]["parking"]), spread
    assert spread[0.0]["lawn"] < 1.3 * spread[0.0]["road"], spread
    assert spread[1.0]["road"] == pytest.approx(spread[0.0]["road"])


def test_crowns_are_taller(towns):
    def aspect(town):  # per tree: height range over horizontal range of its Gaussians
        tree = town.category == CATEGORY["tree"]
        means, ids = town.gaussians.means[tree], town.instance[tree]
        return np.median([np.ptp(means[ids == i, 2]) / np.ptp(means[ids == i, 0]) for i in np.unique(ids)])

    assert aspect(towns[1.0]) > 1.3 * aspect(towns[0.0]), (aspect(towns[0.0]), aspect(towns[1.0]))


def _between_label_share(town: TruthScene, values: np.ndarray, labels: list[str]) -> float:
    """Between-label variance of ``values`` over their total variance (eta squared), over the
    Gaussians of ``labels``."""
    codes = np.array([LABEL[x] for x in labels])
    keep = np.isin(town.label, codes)
    v, lab = values[keep], town.label[keep]
    means = np.array([v[lab == c].mean() for c in codes])
    counts = np.array([(lab == c).sum() for c in codes])
    return float((counts * (means - v.mean()) ** 2).sum() / ((v - v.mean()) ** 2).sum())


def _roughness(means: np.ndarray, cell: float = 1.0) -> np.ndarray:
    """[M] std of z of the Gaussians in each one's ``cell`` m square (a label-free descriptor)."""
    key = np.unique(np.floor(means[:, :2] / cell).astype(np.int64), axis=0, return_inverse=True)[1].ravel()
    count = np.bincount(key)
    mean = np.bincount(key, means[:, 2]) / count
    square = np.bincount(key, means[:, 2] ** 2) / count
    return np.sqrt(np.clip(square - mean**2, 0, None))[key]


def test_ground_labels_differ_in_geometry_only_at_strength_one(towns):
    ground_labels = ["road", "lawn", "parking lot", "pavement", "bare ground"]
    shares = {}
    for strength, town in towns.items():
        ground = np.isin(town.category, [CATEGORY[c] for c in GROUND])
        means = town.gaussians.means
        height = means[:, 2]
        rough = np.zeros(len(means))
        rough[ground] = _roughness(means[ground])
        shares[strength] = (
            _between_label_share(town, height, ground_labels),
            _between_label_share(town, rough, ground_labels),
        )
    assert shares[0.0][0] < 0.01 and shares[1.0][0] > 0.5, shares  # height above the ground plane
    assert shares[1.0][1] > 5 * shares[0.0][1], shares  # local roughness


def test_the_setting_is_validated_recorded_and_deterministic(tmp_path):
    assert "geometry.strength" in world_keys()
    assert with_settings(V2, ["geometry.strength=0.5"]).geometry.strength == 0.5
    assert V1.geometry.strength == 0.0 and V2.geometry.strength == 0.0
    with pytest.raises(ValueError, match="strength"):
        with_settings(V1, ["geometry.strength=1.5"])
    for name in ("a", "b"):
        args = ["sim", "make", "--preset", "tiny", "--seed", "0", "--views", "2", "--out", str(tmp_path / name)]
        assert main([*args, "--world-set", "geometry.strength=1"]) == 0
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert files
    for path in files:
        assert (tmp_path / "a" / path).read_bytes() == (tmp_path / "b" / path).read_bytes(), path
    world = json.loads((tmp_path / "a" / "scene.json").read_text())["options"]["world"]
    assert world["geometry"] == {"strength": 1.0} and world["name"] == "v1+"
    again = _town(0.7, seed=5), _town(0.7, seed=5)
    np.testing.assert_array_equal(again[0].gaussians.means, again[1].gaussians.means)
    assert not np.array_equal(_town(0.7, seed=5).gaussians.means, _town(0.3, seed=5).gaussians.means)


def _figures() -> None:
    """The figures of docs/world.md's "Geometry that follows labels" (seconds)."""
    from olsplat_sim.make import MakeOptions, _town_flight_map

    for strength in (0.0, 0.5, 1.0):
        town = _town(strength)
        ground = np.isin(town.category, [CATEGORY[c] for c in GROUND])
        means = town.gaussians.means
        rough = np.zeros(len(means))
        rough[ground] = _roughness(means[ground])
        labels = ["road", "lawn", "parking lot", "pavement", "bare ground"]
        colours = []
        for seed in range(40):
            layout = generate_layout(130.0, np.random.default_rng(seed))
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=GEOMETRY_WORLD_KEY))
            tie_roof_colors(layout, strength, rng)
            colours += [b.roof_color for b in layout.buildings]
        shares = {c: round(colours.count(c) / len(colours), 2) for c in ROOF_COLORS}
        print(f"S={strength}: over 40 layouts tied shares {_tied_share(strength)}, colour shares {shares}")
        print(f"  tiny seed 0: eta2 height {_between_label_share(town, means[:, 2], labels):.4f}, "
              f"1 m roughness {_between_label_share(town, rough, labels):.4f}; height std "
              f"lawn {np.std(_z(town, 'lawn')):.3f} m, road {np.std(_z(town, 'road')):.3f} m")  # fmt: skip
    for strength in (0.0, 1.0):
        options = MakeOptions(world=with_settings(V1, [f"geometry.strength={strength}"]))
        recon = _town_flight_map(PRESETS["small"], 0, options)[3]
        for label in ("road", "lawn", "pavement"):
            z = recon.gaussians.means[recon.label == LABEL[label], 2]
            q1, q2, q3 = np.percentile(z, [25, 50, 75])
            print(f"S={strength} small map seed 0, {label}: median height {q2:.3f} m, IQR {q3 - q1:.3f} m")


if __name__ == "__main__":
    _figures()


def test_world_v2g_is_v2_with_full_geometry_ties(tmp_path):
    """`sim make --world v2g` records v2's every setting but the geometry strength, which is 1."""
    import dataclasses

    out = tmp_path / "v2g"
    assert (
        main(["sim", "make", "--preset", "tiny", "--seed", "0", "--world", "v2g", "--views", "2", "--out", str(out)])
        == 0
    )
    world = json.loads((out / "scene.json").read_text())["options"]["world"]
    expected = json.loads(json.dumps(dataclasses.asdict(V2)))
    assert world["name"] == "v2g" and world["geometry"] == {"strength": 1.0}
    assert {k: v for k, v in world.items() if k not in ("name", "geometry")} == {
        k: v for k, v in expected.items() if k not in ("name", "geometry")
    }
