"""The page's "Download GeoJSON": a run folder's answer (``review.RunReview`` over the query
service) carries its 3D instances in WGS-84 when the prior map has a georef.json, and
``answer_geojson`` gives the file the page sends (valid for the geojson package); without a
georeference the page offers none."""

from __future__ import annotations

import shutil

import geojson
import pytest

from olsplat_nodes.ground.review import RunReview, answer_geojson
from tests.nodes.conftest import region_features, tiny_camera, tiny_run  # noqa: F401  (fixtures)

pytestmark = pytest.mark.timeout(120)


def test_run_review_answer_offers_geojson_only_with_a_georeference(tiny, tiny_run, tmp_path):  # noqa: F811
    scene, _ = tiny
    review = RunReview(tiny_run, scene / "map" / "point_cloud.ply", 1000)
    try:
        review.refresh()  # the page's first poll: the run's newest map
        answer = review.ask("parking lot", ["road", "trees", "lawn"])
    finally:
        review.close()
    assert answer.status == "ok" and answer.instances and answer.height_ref == "ellipsoid"
    collection = geojson.loads(answer_geojson(answer))
    assert collection.is_valid and len(collection["features"]) == len(answer.instances)
    assert collection["features"][0]["properties"]["query"] == "parking lot"

    bare = tmp_path / "map"
    bare.mkdir()
    shutil.copy(scene / "map" / "point_cloud.ply", bare)  # the same map without its georef.json
    review = RunReview(tiny_run, bare / "point_cloud.ply", 1000)
    try:
        review.refresh()  # the page's first poll: the run's newest map
        answer = review.ask("parking lot", ["road", "trees", "lawn"])
    finally:
        review.close()
    assert answer.status == "ok" and answer.instances and answer.height_ref == ""
    assert answer_geojson(answer) is None
