"""Tiles: a view split by ground tile keeps every observation once, and the union of the tiles'
maps is the single store's map (the tiny flight with 1 and 4 tiles)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from olsplat_nodes.aggregate import ViewObservations
from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.pipeline.offline import aggregate_flights
from olsplat_nodes.storage import LanguageMap, ObservationStore
from olsplat_nodes.storage.tiles import TiledStore, TileGrid, Tiling, split_view


def _random_view(rng, n_map: int, kept: int, regions: int, dim: int) -> tuple[ViewObservations, np.ndarray]:
    ids = np.sort(rng.choice(n_map, kept, replace=False)).astype(np.int32)
    counts = rng.integers(1, 4, kept)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    slots = rng.integers(0, regions, offsets[-1]).astype(np.int32)
    weights = rng.uniform(0.1, 1.0, offsets[-1]).astype(np.float32)
    strength = rng.uniform(0.1, 1.0, kept).astype(np.float32)
    return ViewObservations(ids, strength, offsets, slots, weights), rng.normal(size=(regions, dim)).astype(np.float32)


def test_a_split_view_keeps_each_observation_once_in_its_tile():
    rng = np.random.default_rng(0)
    means = rng.uniform(-150, 150, (500, 3))
    tiling = Tiling.of(means, TileGrid(100.0))
    assert len(tiling) == 16  # x and y in [-150, 150): cells -2..1 on each axis
    for t, members in enumerate(tiling.members):
        assert (np.diff(members) > 0).all() and (tiling.tile[members] == t).all()
        np.testing.assert_array_equal(tiling.local[members], np.arange(len(members)))
        cells = np.floor(means[members, :2] / 100.0)
        assert (cells == cells[0]).all()  # one ground cell per tile
    view, bank = _random_view(rng, 500, 120, 30, 6)
    dense = view.features(bank)
    parts = split_view(tiling, view, bank)
    seen = []
    for t, (part, part_bank) in parts.items():
        back = tiling.members[t][part.gaussians]  # the part's rows are the tile's own
        rows = np.searchsorted(view.gaussians, back)
        np.testing.assert_array_equal(view.gaussians[rows], back)
        np.testing.assert_array_equal(part.strength, view.strength[rows])
        np.testing.assert_allclose(part.features(part_bank), dense[rows], rtol=1e-6)
        assert len(part_bank) == len(np.unique(part.slots))  # only the bank rows the tile uses
        seen.extend(back.tolist())
    assert sorted(seen) == view.gaussians.tolist()


def test_one_tile_is_the_whole_map_and_its_store_the_folder_itself(tmp_path):
    means = np.random.default_rng(1).uniform(-500, 500, (50, 3))
    tiling = Tiling.of(means, TileGrid(0.0))
    assert len(tiling) == 1 and tiling.members[0].tolist() == list(range(50))
    assert TiledStore(tmp_path, tiling, writer=True).shard_folder(0) == tmp_path


def test_a_view_sent_again_is_recorded_once_and_another_tiling_is_refused(tmp_path):
    rng = np.random.default_rng(2)
    means = rng.uniform(-150, 150, (300, 3))
    store = TiledStore(tmp_path, Tiling.of(means, TileGrid(100.0)), writer=True)
    view, bank = _random_view(rng, 300, 80, 10, 4)
    first = store.append("frame_0000.jpg", view, bank)
    assert first and store.append("frame_0000.jpg", view, bank) == []
    again = TiledStore(tmp_path, Tiling.of(means, TileGrid(100.0)), writer=True)  # a restarted writer
    assert again.append("frame_0000.jpg", view, bank) == [] and len(again) == 1
    assert sum(len(ObservationStore(again.shard_folder(t), 1)) for t in range(len(again.tiling))) == len(first)
    with pytest.raises(OlsplatInputError, match=r"tiles\.json.*50"):
        TiledStore(tmp_path, Tiling.of(means, TileGrid(50.0)))
    with pytest.raises(OlsplatInputError, match="tile size"):
        TileGrid(-1.0)


@pytest.fixture(scope="module")
def tiny_copy(tiny, tmp_path_factory):
    """A private copy of the tiny flight: its encode cache is written here, never into the
    session's shared folder (whose bytes ``tests/sim`` checks)."""
    copy = tmp_path_factory.mktemp("tiles") / "scene"
    shutil.copytree(tiny[0], copy, ignore=shutil.ignore_patterns("cache"))
    return copy


@pytest.fixture(scope="module")
def tiny_views(tiny_copy):
    """The tiny flight's views, observed once: [(name, observations, stacked bank)]."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.method import named_method, view_observations
    from olsplat_nodes.pipeline import Scene, view_features
    from olsplat_nodes.scene import read_ply

    scene = Scene.open(tiny_copy)
    gaussians, method, encoder = read_ply(scene.ply), named_method("outlangsplat"), encoder_from_spec()
    views = []
    for camera in scene.cameras:
        label_maps, bank = view_features(scene, camera, encoder)
        observations, stacked, _ = view_observations(gaussians, camera, label_maps, bank, method)
        views.append((camera.name, observations, stacked))
    return gaussians, method, views


@pytest.mark.parametrize("tile_m", [0.0, 100.0])
def test_the_tiled_map_equals_the_single_store_map(tiny_views, tmp_path, tile_m):
    """The tiny town spans x, y in about [-52, 52] m: 100 m tiles on the grid anchored at 0 make
    four, one per quadrant. Every row is bit-identical to the plain store's (float16 unit rows)."""
    gaussians, method, views = tiny_views
    single = ObservationStore(tmp_path / "single", len(gaussians), writer=True)
    tiled = TiledStore(tmp_path / "tiled", Tiling.of(gaussians.means, TileGrid(tile_m)), writer=True)
    for name, observations, stacked in views:
        single.append(name, observations, stacked)
        tiled.append(name, observations, stacked)
    expected, expected_observed = single.refine(None, method.aggregation, only_touched=False, unit_float16=True)
    got, observed = tiled.refine(method.aggregation)
    assert len(tiled.tiling) == (1 if tile_m == 0 else 4)
    assert expected is not None and got is not None and expected_observed.sum() > 1000
    np.testing.assert_array_equal(observed, expected_observed)
    np.testing.assert_array_equal(got, expected)
    if tile_m:  # each tile holds only its part: no tile stores a view's whole observations
        name, first = views[0][0], views[0][1]
        shards = [ObservationStore(tiled.shard_folder(t), 1) for t in range(4)]
        sizes = [len(s.load(s.names().index(name))[0]) for s in shards if name in s.names()]
        assert sum(sizes) == len(first) and max(sizes) < len(first)


def test_two_flights_of_one_map_make_one_map_and_another_map_is_refused(tiny, tmp_path):
    """Two flights over one prior map (here the same flight twice, under two folders): each view
    is recorded once per flight, and a flight over another map is one clear error."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.method import named_method
    from olsplat_nodes.pipeline import Scene

    for name in ("a", "b"):
        shutil.copytree(tiny[0], tmp_path / name, ignore=shutil.ignore_patterns("cache"))
    scenes = [Scene.open(tmp_path / name) for name in ("a", "b")]
    scenes = [Scene(s.folder, s.ply, s.cameras[:3]) for s in scenes]
    stats = aggregate_flights(scenes, named_method("outlangsplat"), encoder_from_spec(), tmp_path / "out", tile_m=100.0)
    assert stats["tiles"] == 4
    tiles = [p for p in (tmp_path / "out" / "store").iterdir() if p.is_dir()]
    names = set().union(*[set(ObservationStore(p, 1).names()) for p in tiles])
    assert names == {f"f{i}/{c.name}" for i in (0, 1) for c in scenes[0].cameras}
    shutil.copytree(tiny[0], tmp_path / "other", ignore=shutil.ignore_patterns("cache"))
    ply = tmp_path / "other" / "map" / "point_cloud.ply"
    from olsplat_nodes.scene import read_ply, write_ply

    write_ply(ply, read_ply(ply).subset(np.arange(100)))
    with pytest.raises(OlsplatInputError, match="not the prior map"):
        aggregate_flights(
            [scenes[0], Scene.open(tmp_path / "other")], named_method("outlangsplat"), None, tmp_path / "x"
        )


def test_a_tiled_map_answers_a_query_tile_by_tile_as_the_whole_map(tiny_copy, tmp_path, capsys):
    """``olsplat query --map DIR`` on a 4-tile aggregation: every tile's map asked in turn. The
    Gaussians that pick the text are the whole map's, exactly; each instance lies in one tile,
    and together they hold the whole map's instances' Gaussians but those cut by a tile border
    into parts below min_points."""
    from olsplat_nodes.cli import main
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.method import named_method
    from olsplat_nodes.pipeline import Scene
    from olsplat_nodes.query.answer import answer_query, encoder_for_map
    from olsplat_nodes.query.tiled import answer_tiled, tile_maps
    from olsplat_nodes.scene import read_ply

    scene = Scene.open(tiny_copy)
    for tile_m, out in ((100.0, tmp_path / "tiled"), (0.0, tmp_path / "whole")):
        aggregate_flights([scene], named_method("outlangsplat"), encoder_from_spec(), out, tile_m=tile_m)
    assert len(tile_maps(tmp_path / "tiled")) == 4 and not tile_maps(tmp_path / "whole")
    gaussians = read_ply(scene.ply)
    whole = LanguageMap.load(tmp_path / "whole" / "language_map.npz")
    encoder = encoder_for_map(whole)
    negatives = ["road", "trees", "lawn", "cars"]
    expected = answer_query(whole, gaussians, encoder, "red roof buildings", negatives, cluster_radius=3.0)
    got = answer_tiled(tmp_path / "tiled", gaussians, encoder, "red roof buildings", negatives, cluster_radius=3.0)
    assert got.chosen == expected.chosen_count > 0 and len(got.tiles) == 4
    for instance in got.instances:  # DBSCAN ran within a tile
        low, high = np.floor(np.array(instance.box_min[:2]) / 100.0), np.floor(np.array(instance.box_max[:2]) / 100.0)
        assert (low == high).all()
    assert sum(i.gaussians for i in got.instances) <= expected.chosen_count
    assert len(got.instances) >= len(expected.instances) > 0
    args = ["--negatives", ",".join(negatives), "--cluster-radius", "3"]
    code = main(["query", "--map", str(tmp_path / "tiled"), "--scene", str(tiny_copy), "red roof buildings", *args])
    printed = capsys.readouterr().out
    assert code == 0 and f"{expected.chosen_count:,} Gaussians pick it" in printed and "from 4 tiles" in printed
