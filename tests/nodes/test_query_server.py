"""The query server before any map exists: an explicit "no_map" at once (not a hang), for a query
with and without a view; a StatusRequest works before any map; and once a snapshot appears
(the refiner's latest.json), the same server answers from it without a restart, after querying
it once in the background (status value ``query_warm``). With a map, the
instances of its reply are, byte for byte, the ``Instance`` records msgs/README.md documents,
their latitude, longitude and altitudes those of the map's georef.json."""

from __future__ import annotations

import shutil
import time

import msgpack
import numpy as np
import pymap3d
import pytest

from olsplat_msgs import MapUpdated, QueryReply, QueryRequest, StatusReply, StatusRequest, decode, encode, load_schema
from olsplat_nodes.transport import QueryClient
from olsplat_sim.make import TOWN_GEOREF
from tests.helpers import every, wait_for

from .conftest import ENCODE_VIEW, NodeThread, query_server, raw_socket, send_msg

pytestmark = pytest.mark.timeout(120)


def test_no_map_yet_is_answered_at_once_and_status_works(ctx, sockdir, tiny, tiny_run, tmp_path):
    import zmq

    scene, _ = tiny
    endpoint = f"ipc://{sockdir}/query.sock"
    maps = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/map.sock", bind=True)
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views")
    try:
        with NodeThread(node) as running, QueryClient(ctx, endpoint, timeout_s=10.0) as client:
            status = client.request(StatusRequest(request_id="s1"))  # also waits for the node to be up
            assert isinstance(status, StatusReply) and status.request_id == "s1" and status.map_version == 0
            assert status.nodes[0]["node"] == "query_server" and status.nodes[0]["level"] == 0
            assert "map version 0" in status.nodes[0]["message"]
            assert status.nodes[0]["values"]["query_warm"] == 0  # nothing to warm without a map

            client.timeout_s = 2.0  # "at once": a hang would raise NoReply
            for view in ("", ENCODE_VIEW):
                start = time.monotonic()
                reply = client.request(
                    QueryRequest(request_id=f"q-{view}", text="red roof buildings", view=view, heatmap=bool(view))
                )
                elapsed = time.monotonic() - start
                assert isinstance(reply, QueryReply) and reply.request_id == f"q-{view}"
                assert reply.status == "no_map" and "no map yet" in reply.message and elapsed < 1.0
                assert reply.map_version == 0 and reply.view == view and reply.instances == []
                assert reply.heatmap is None and reply.mask is None and reply.image is None

            # the refiner writes its first snapshot and announces it: answered from it, no restart
            shutil.copytree(tiny_run / "views", tmp_path / "views")
            shutil.copytree(tiny_run / "map", tmp_path / "staging")
            (tmp_path / "staging").rename(tmp_path / "map")  # appears at once, as the refiner's atomic writes do
            wait_for(
                lambda: client.request(StatusRequest()).map_version == 1,
                10,
                "the first map to be loaded",
                step=every(
                    0.2, lambda: send_msg(maps, MapUpdated(version=1, path=str(tmp_path / "map"), views=1), "map")
                ),
            )
            # the first map is queried in the background: the operator's first query finds the
            # text encoder loaded (and the kernels warm)
            wait_for(
                lambda: client.request(StatusRequest()).nodes[0]["values"]["query_warm"] == 1, 60, "the warm query"
            )
            service = node.service  # the map and its caches (query/service.py)
            assert list(service.encoders) == [service.language_map.encoder] and service.warm_query.result() > 0
            client.timeout_s = 30.0
            reply = client.request(
                QueryRequest(request_id="q", text="red roof buildings", view=ENCODE_VIEW, heatmap=True)
            )
            assert reply.status == "ok" and reply.map_version == 1 and reply.heatmap.shape == (240, 320)
            assert not reply.preview and "Gaussians pick it" in reply.message
            # a preview (request.preview): the view's pictures at most PREVIEW_MAX_SIDE px, no 3D
            # instances, no splat margin; refused without a view and on a change query
            node.service.heatmap_max_side = 200  # the server's own limit binds when it is smaller
            preview = client.request(
                QueryRequest(request_id="p", text="red roof buildings", view=ENCODE_VIEW, preview=True, splats=1000)
            )
            assert preview.status == "ok" and preview.preview and preview.request_id == "p"
            assert preview.heatmap.shape == preview.mask.shape == (150, 200) and preview.image.shape == (150, 200, 3)
            assert [i["kind"] for i in preview.instances] == ["2d"] * len(preview.instances)
            assert preview.splat_margin is None and "preview of view" in preview.message
            for bad in (QueryRequest(text="roads", preview=True), QueryRequest(text="", since="f0", preview=True)):
                refused = client.request(bad)
                assert refused.status == "bad_request" and not refused.preview, refused.message
            running.assert_running()
    finally:
        maps.close()


# The documented Instance record (msgs/README.md, "Records"), written out here so that the test
# does not trust the codec it checks: key -> (type, length of the list or None).
INSTANCE_3D = {
    "id": (int, None),
    "kind": (str, None),
    "n_gaussians": (int, None),
    "centroid": (float, 3),
    "box_min": (float, 3),
    "box_max": (float, 3),
    "latitude": (float, None),
    "longitude": (float, None),
    "altitude": (float, None),
    "footprint": (float, 8),
    "box_altitude": (float, 2),
}
INSTANCE_2D = {
    "id": (int, None),
    "kind": (str, None),
    "box2d": (int, 4),
    "centre_px": (float, 2),
    "area_px": (int, None),
}


def corners_ccw(lo, hi):
    """The box's lower corners counter-clockwise seen from above (x east, y north)."""
    return [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]


def _check_types(instance: dict, spec: dict) -> None:
    assert list(instance) == list(spec), instance  # exactly these keys, in the documented order
    for key, (kind, length) in spec.items():
        value = instance[key]
        if length is None:
            assert type(value) is kind, (key, value)
        else:
            assert type(value) is list and len(value) == length and all(type(x) is kind for x in value), (key, value)


def test_reply_instances_on_the_wire_are_the_documented_records(ctx, sockdir, tiny, tiny_run, tmp_path):
    import zmq

    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")  # a snapshot from the start: loaded at once
    endpoint = f"ipc://{sockdir}/query.sock"
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views")
    dealer = raw_socket(ctx, zmq.DEALER, endpoint, bind=False)  # raw frames: what any client receives
    try:
        with NodeThread(node) as running:
            request = QueryRequest(request_id="rec", text="parking lot", view=ENCODE_VIEW, heatmap=True)
            dealer.send_multipart([b"", *encode(request, "query")])
            assert dealer.poll(60_000), "no reply from the query server"
            frames = dealer.recv_multipart()
            running.assert_running()
    finally:
        dealer.close()
    assert frames[0] == b"" and frames[1] == b"query"
    header = msgpack.unpackb(frames[2], raw=False)
    assert header["schema"] == "olsplat_msgs/QueryReply" and header["fields"]["status"] == "ok", header["fields"]
    assert header["fields"]["height_ref"] == "ellipsoid"  # the town's georeference (sim make)
    instances = header["fields"]["instances"]
    found3d = [i for i in instances if i.get("kind") == "3d"]
    found2d = [i for i in instances if i.get("kind") == "2d"]
    assert found3d and found2d and instances == found3d + found2d  # every 3D instance first, then the regions

    schema = load_schema().records["Instance"]
    assert list(INSTANCE_3D) == [f.name for f in schema.fields_of("3d")]
    assert list(INSTANCE_2D) == [f.name for f in schema.fields_of("2d")]
    for instance in found3d:
        _check_types(instance, INSTANCE_3D)
        lo, c, hi = (np.array(instance[k]) for k in ("box_min", "centroid", "box_max"))
        assert np.isfinite([lo, c, hi]).all() and (lo <= c).all() and (c <= hi).all()
        assert instance["n_gaussians"] >= 20  # the clustering's min_points
        # the place on the Earth: the simulated town's georef.json beside the prior map, checked
        # here with pymap3d directly (not through the server's code)
        lat, lon, alt = pymap3d.enu2geodetic(*c, *TOWN_GEOREF.origin)
        assert (instance["latitude"], instance["longitude"]) == pytest.approx((lat, lon), abs=1e-9)
        assert instance["altitude"] == pytest.approx(alt, abs=1e-6)
        corners = [pymap3d.enu2geodetic(x, y, lo[2], *TOWN_GEOREF.origin)[1::-1] for x, y in corners_ccw(lo, hi)]
        np.testing.assert_allclose(np.reshape(instance["footprint"], (4, 2)), corners, atol=1e-9)
        assert instance["box_altitude"] == pytest.approx([lo[2] + 488.0, hi[2] + 488.0], abs=0.01)
    for instance in found2d:
        _check_types(instance, INSTANCE_2D)
        x0, y0, x1, y1 = instance["box2d"]
        assert 0 <= x0 < x1 <= 320 and 0 <= y0 < y1 <= 240  # the view's pixel grid, end exclusive
        x, y = instance["centre_px"]
        assert x0 + 0.5 <= x <= x1 - 0.5 and y0 + 0.5 <= y <= y1 - 0.5  # pixel centres at +0.5
        assert 50 <= instance["area_px"] <= (x1 - x0) * (y1 - y0)
    for found, size in ((found3d, "n_gaussians"), (found2d, "area_px")):
        assert [i["id"] for i in found] == list(range(len(found)))
        assert [i[size] for i in found] == sorted((i[size] for i in found), reverse=True)

    _, reply = decode(frames[1:])  # the codec reads the same records back
    assert reply.instances == instances and reply.request_id == "rec"
    mask = reply.mask.astype(bool)
    assert mask.shape == (240, 320) and sum(i["area_px"] for i in found2d) <= mask.sum()
    biggest = found2d[0]
    x0, y0, x1, y1 = biggest["box2d"]
    assert mask[y0:y1, x0:x1].any(axis=0)[[0, -1]].all() and mask[y0:y1, x0:x1].any(axis=1)[[0, -1]].all()  # tight box


def test_reply_arrays_mean_what_the_schema_says(ctx, sockdir, tiny, tiny_run, tmp_path):
    """heatmap: the cosine of the view's rendered features with the query, in [-1, 1]; mask:
    where that beats every negative's heatmap on covered pixels; image: the view's photo."""
    from olsplat_nodes.query.answer import encoder_for_map
    from olsplat_nodes.query.heatmap import FeatureImages, render_heatmaps
    from olsplat_nodes.scene import read_ply
    from olsplat_nodes.storage import LanguageMap, latest_map, load_views

    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")
    negatives = ["road", "trees", "lawn"]
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views")
    with NodeThread(node) as running, QueryClient(ctx, f"ipc://{sockdir}/query.sock", timeout_s=60.0) as client:
        reply = client.request(
            QueryRequest(request_id="m", text="red roof buildings", view=ENCODE_VIEW, negatives=negatives)
        )
        running.assert_running()
    assert reply.status == "ok", reply.message
    fields = {f.name: f for f in load_schema().messages["QueryReply"].fields}
    assert "cosine" in fields["heatmap"].description and "[-1, 1]" in fields["heatmap"].description
    assert "photo" in fields["image"].description

    language_map = LanguageMap.load(latest_map(tmp_path / "map")["path"])
    view = next(v for v in load_views(tmp_path / "views") if v.camera.name == ENCODE_VIEW)
    texts = encoder_for_map(language_map).encode_text(["red roof buildings", *negatives])
    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    features = language_map.features.astype(np.float32)
    rendered, _ = render_heatmaps(gaussians, features, texts, view.camera)  # eq. semantic_heatmap in the kernel
    # the server keeps the view's rendered features for the next query: the same sums, the
    # cosine by a matrix product (to the bit as a fresh cache's, to 2e-5 as the kernel's)
    maps, alpha = FeatureImages(2**30).heatmaps("k", gaussians, features, texts, view.camera)
    assert reply.heatmap.dtype == np.float32 and np.abs(reply.heatmap).max() <= 1.0 + 1e-5
    np.testing.assert_array_equal(reply.heatmap, maps[0])
    np.testing.assert_allclose(maps, rendered, atol=2e-5)
    expected_mask = (maps[0] > maps[1:].max(0)) & (alpha > 0.5)
    np.testing.assert_array_equal(reply.mask.astype(bool), expected_mask)
    np.testing.assert_array_equal(reply.image, view.image())


def test_too_many_or_too_long_negatives_get_a_clear_refusal(ctx, sockdir, tiny, tiny_run, tmp_path):
    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views", max_negatives=4)
    with NodeThread(node) as running, QueryClient(ctx, f"ipc://{sockdir}/query.sock", timeout_s=60.0) as client:
        many = client.request(QueryRequest(request_id="n", text="road", negatives=[f"thing {i}" for i in range(1000)]))
        long = client.request(QueryRequest(request_id="l", text="road", negatives=["x" * 201]))
        fine = client.request(QueryRequest(request_id="f", text="road", negatives=["trees", "lawn", "cars", "roof"]))
        running.assert_running()
    assert many.status == "bad_request" and many.message == "1000 negatives; at most 4 per query"
    assert long.status == "bad_request" and "longer than 200 characters" in long.message
    assert fine.status == "ok", fine.message


def test_a_heatmap_reply_over_the_size_limit_is_refused_with_its_size(ctx, sockdir, tiny, tiny_run, tmp_path):
    """One view per query (the request has one ``view`` field); its reply (heatmap, mask, photo:
    8 bytes per pixel) must fit ``max_reply_mb``, or the request is refused saying why."""
    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views", max_reply_mb=0.5)
    with NodeThread(node) as running, QueryClient(ctx, f"ipc://{sockdir}/query.sock", timeout_s=60.0) as client:
        big = client.request(QueryRequest(request_id="b", text="road", view=ENCODE_VIEW, heatmap=True))
        small = client.request(QueryRequest(request_id="s", text="road", view=ENCODE_VIEW, heatmap=False))
        running.assert_running()
    assert big.status == "bad_request" and big.heatmap is None
    assert big.message == f"view {ENCODE_VIEW} is 320x240: its heatmap reply would be 0.6 MB, over max_reply_mb 0.5"
    assert small.status == "ok" and small.heatmap is None  # without the heatmap the view costs nothing


def test_a_capped_reply_is_the_view_rendered_at_that_size(ctx, sockdir, tiny, tiny_run, tmp_path):
    """With heatmap_max_side the heatmap, mask and photo of the reply are on one grid, the view
    scaled down to that longer side: the heatmap is the render of the scaled camera (not a
    resampled full-size one), the photo the view's, area-averaged."""
    import cv2

    from olsplat_nodes.query.answer import encoder_for_map
    from olsplat_nodes.query.heatmap import FeatureImages
    from olsplat_nodes.scene import read_ply
    from olsplat_nodes.storage import LanguageMap, latest_map, load_views

    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")
    negatives = ["road", "trees", "lawn"]
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views", heatmap_max_side=160)
    with NodeThread(node) as running, QueryClient(ctx, f"ipc://{sockdir}/query.sock", timeout_s=60.0) as client:
        reply = client.request(QueryRequest(request_id="c", text="parking lot", view=ENCODE_VIEW, negatives=negatives))
        running.assert_running()
    assert reply.status == "ok", reply.message
    view = next(v for v in load_views(tmp_path / "views") if v.camera.name == ENCODE_VIEW)
    assert (view.camera.width, view.camera.height) == (320, 240)
    assert reply.heatmap.shape == reply.mask.shape == (120, 160) and reply.image.shape == (120, 160, 3)
    np.testing.assert_array_equal(reply.image, cv2.resize(view.image(), (160, 120), interpolation=cv2.INTER_AREA))

    language_map = LanguageMap.load(latest_map(tmp_path / "map")["path"])
    texts = encoder_for_map(language_map).encode_text(["parking lot", *negatives])
    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    small = view.camera.scaled(0.5)
    maps, alpha = FeatureImages(2**30).heatmaps("k", gaussians, language_map.features.astype(np.float32), texts, small)
    np.testing.assert_allclose(reply.heatmap, maps[0], atol=2e-5)
    expected_mask = (maps[0] > maps[1:].max(0)) & (alpha > 0.5)
    assert (reply.mask.astype(bool) != expected_mask).mean() < 1e-3  # ties within the 2e-5 may flip a pixel
    assert reply.mask.any()
    for instance in reply.instances:
        if instance["kind"] == "2d":
            x0, y0, x1, y1 = instance["box2d"]
            assert 0 <= x0 < x1 <= 160 and 0 <= y0 < y1 <= 120


def test_a_query_without_negatives_beats_the_aerial_vocabulary_and_says_so(ctx, sockdir, tiny, tiny_run, tmp_path):
    """The live default: the query must beat the land-cover classes of an aerial scene (not
    "object", "things"), the reply's message names them, and the roof query no longer marks
    road and bare ground: its mask is the one the offline query with the flight's labels makes."""
    from olsplat_nodes.evaluate.scene_eval import label_texts, load_queries
    from olsplat_nodes.query import CANONICAL_NEGATIVES
    from olsplat_nodes.query.answer import answer_query, encoder_for_map
    from olsplat_nodes.query.negatives import AERIAL_VOCABULARY
    from olsplat_nodes.scene import read_ply
    from olsplat_nodes.storage import LanguageMap, latest_map, load_views

    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views")
    with NodeThread(node), QueryClient(ctx, f"ipc://{sockdir}/query.sock", timeout_s=60.0) as client:
        reply = client.request(QueryRequest(request_id="d", text="red roof buildings", view=ENCODE_VIEW))
    assert reply.status == "ok", reply.message
    used = [n for n in AERIAL_VOCABULARY if n != "red roof buildings"]
    assert f"over {len(used)} negatives ({', '.join(used)})" in reply.message

    language_map = LanguageMap.load(latest_map(tmp_path / "map")["path"])
    view = next(v for v in load_views(tmp_path / "views") if v.camera.name == ENCODE_VIEW)
    gaussians, encoder = read_ply(scene / "map" / "point_cloud.ply"), encoder_for_map(language_map)
    labels, queries = load_queries(scene)
    own = [t for t in label_texts(labels, queries) if t != "red roof buildings"]
    offline = answer_query(language_map, gaussians, encoder, "red roof buildings", own, view.camera).mask
    generic = answer_query(language_map, gaussians, encoder, "red roof buildings", CANONICAL_NEGATIVES, view.camera)
    np.testing.assert_array_equal(reply.mask.astype(bool), offline)
    assert generic.mask.mean() > 5 * max(offline.mean(), 0.002)  # what the old default marked


def test_vocabulary_negatives_drop_the_query_and_its_near_duplicates():
    from olsplat_nodes.query.negatives import AERIAL_VOCABULARY, vocabulary_negatives

    class Words:  # text embeddings by hand: one axis per text, but "roofs" is "red roof buildings"
        def encode_text(self, texts):
            axes = [*AERIAL_VOCABULARY, "road", "Road"]
            rows = np.zeros((len(texts), len(axes)), np.float32)
            for i, text in enumerate(texts):
                rows[i, axes.index("red roof buildings" if text == "roofs" else text)] = 1.0
            return rows

    assert vocabulary_negatives("Road", Words()) == [v for v in AERIAL_VOCABULARY if v != "road"]
    assert "red roof buildings" not in vocabulary_negatives("roofs", Words())
    assert vocabulary_negatives("road", Words(), vocabulary=["road"]) == ["object", "things", "stuff", "texture"]
