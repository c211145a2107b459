"""Answers in WGS-84 end to end, on the tiny simulated flight aggregated offline (12 views): a
real query server over a run's map folder answers ``olsplat ground query "red roof buildings"
--geojson F --kml K``, and ``olsplat query --map RUN/map`` writes the same; the files are read
by the geojson package and the standard library, and the red roof building the flight saw
(queries.json, its truth Gaussians) lies within 1 m of the first feature's centre, inside its
footprint. Without a georeference --geojson is refused in one line."""

from __future__ import annotations

import json
import shutil
from xml.etree import ElementTree

import geojson
import numpy as np
import pymap3d
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.scene import read_ply
from olsplat_nodes.storage import LanguageMap, write_snapshot
from olsplat_sim.make import TOWN_GEOREF

from .test_ground_cli import ground, query_server, wait_until_up

pytestmark = pytest.mark.timeout(180)
QUERY = "red roof buildings"


@pytest.fixture(scope="module")
def run_dir(tiny_map, tmp_path_factory):
    """A run folder whose map/ holds the offline map as snapshot version 1 (views/ empty)."""
    run = tmp_path_factory.mktemp("geo_run")
    language_map = LanguageMap.load(tiny_map)
    record = {"views": 12, "observed_gaussians": int(language_map.observed.sum()), "final": True}
    write_snapshot(run / "map", 1, language_map, {**record, "encoder": language_map.encoder}, None)
    (run / "views").mkdir()
    return run


def negatives(scene) -> str:
    labels = json.loads((scene / "queries.json").read_text())["labels"]
    return ",".join(label for label in labels if label != QUERY)


def building_truth(scene) -> tuple[np.ndarray, float, float]:
    """(footprint centre [x, y] metres, lat, lon) of the red roof building the flight saw."""
    queries = json.loads((scene / "queries.json").read_text())["queries"]
    (instance,) = next(q["instances"] for q in queries if q["text"] == QUERY)
    means = read_ply(scene / "truth" / "ground_truth.ply").means
    members = means[np.load(scene / "truth" / "ground_truth_labels.npz")["instance"] == instance]
    centre = (members[:, :2].min(0) + members[:, :2].max(0)) / 2
    lat, lon, _ = pymap3d.enu2geodetic(centre[0], centre[1], 0.0, *TOWN_GEOREF.origin)
    return centre, float(lat), float(lon)


def check_features(path, scene) -> None:
    collection = geojson.loads(path.read_text())
    assert collection.is_valid and collection["features"], collection
    first = collection["features"][0]
    assert first["properties"]["query"] == QUERY and first["properties"]["rank"] == 0
    assert first["properties"]["map_version"] == 1 and first["properties"]["height_ref"] == "ellipsoid"
    polygon = first["geometry"]
    lon, lat, _alt = first["properties"]["centre"]
    _, truth_lat, truth_lon = building_truth(scene)
    east, north, _ = pymap3d.geodetic2enu(lat, lon, 488.0, truth_lat, truth_lon, 488.0)
    assert np.hypot(east, north) < 1.0, f"the feature's centre is {np.hypot(east, north):.2f} m from the building's"
    ring = np.array(polygon["coordinates"][0])
    assert (ring[0] == ring[-1]).all()
    assert ring[:, 0].min() < truth_lon < ring[:, 0].max() and ring[:, 1].min() < truth_lat < ring[:, 1].max()


def test_ground_query_and_query_write_features_on_the_building(ctx, sockdir, tiny, run_dir, tmp_path, capsys):
    scene, _ = tiny
    with query_server(ctx, sockdir, tiny, run_dir / "map", run_dir / "views") as endpoint:
        wait_until_up(capsys, endpoint)
        argv = ["query", QUERY, "--negatives", negatives(scene), "--connect", endpoint, "--timeout", 60]
        code, out, err = ground(capsys, *argv, "--geojson", tmp_path / "ground.geojson", "--kml", tmp_path / "g.kml")
        assert code == 0, err
        assert "lat 47.39" in out and f"-> {tmp_path / 'ground.geojson'}" in out
        code, out, err = ground(capsys, *argv, "--json", "--geojson", tmp_path / "json.geojson")
        assert code == 0 and json.loads(out)["height_ref"] == "ellipsoid" and "->" in err
    check_features(tmp_path / "ground.geojson", scene)
    placemarks = ElementTree.parse(tmp_path / "g.kml").getroot().iter("{http://www.opengis.net/kml/2.2}Placemark")
    assert len(list(placemarks)) == len(geojson.loads((tmp_path / "ground.geojson").read_text())["features"])

    # the offline command, over the run's map folder (its latest snapshot): the same answer
    args = ["query", "--map", str(run_dir / "map"), "--scene", str(scene), QUERY, "--negatives", negatives(scene)]
    code = main([*args, "--geojson", str(tmp_path / "q")])
    out, err = capsys.readouterr()
    assert code == 0, err
    check_features(tmp_path / "q", scene)
    ground_features = geojson.loads((tmp_path / "ground.geojson").read_text())["features"]
    query_features = geojson.loads((tmp_path / "q").read_text())["features"]
    assert len(query_features) == len(ground_features)
    for mine, theirs in zip(query_features, ground_features, strict=True):  # float32 sums: cm apart at most
        a, b = (np.array(f["properties"]["centre"]) for f in (mine, theirs))
        assert np.abs(a[:2] - b[:2]).max() < 1e-6 and abs(a[2] - b[2]) < 0.05


def test_geojson_without_a_georeference_is_refused_in_one_line(tiny, run_dir, tmp_path, capsys):
    scene, _ = tiny
    bare = tmp_path / "scene"
    shutil.copytree(scene, bare, ignore=shutil.ignore_patterns("georef.json", "replay.mcap", "truth", "preview"))
    code = main(["query", "--map", str(run_dir / "map"), "--scene", str(bare), QUERY, "--geojson", str(tmp_path / "f")])
    _, err = capsys.readouterr()
    assert code == 1 and err.count("\n") == 1 and "georef.json" in err and "olsplat map georef" in err
    assert not (tmp_path / "f").exists()
