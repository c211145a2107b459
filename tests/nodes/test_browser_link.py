"""What the browser ground station asks over the ground link (msgs/README.md, "The query link"),
against a real query server node: the decimated prior map (SplatsRequest), the views' cameras
in pages (ViewsRequest), a query's per-splat relevance (QueryRequest.splats) and the loaded
map's figures in the server's status; then the page's source (``ground.link.LinkSource``) over
that link, and over a link where nothing answers."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from olsplat_msgs import QueryRequest, SplatsReply, SplatsRequest, StatusRequest, ViewsReply, ViewsRequest
from olsplat_nodes.transport import QueryClient

from .conftest import ENCODE_VIEW, NodeThread, query_server

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def served(ctx, sockdir, tiny, tiny_run, tmp_path):
    """A query server over the tiny run's map and views, and a client of it."""
    scene, _ = tiny
    shutil.copytree(tiny_run / "views", tmp_path / "views")
    shutil.copytree(tiny_run / "map", tmp_path / "map")
    node = query_server(scene, sockdir, tmp_path / "map", tmp_path / "views")
    with NodeThread(node) as running, QueryClient(ctx, f"ipc://{sockdir}/query.sock", timeout_s=60.0) as client:
        yield scene, tmp_path, client
        running.assert_running()


def test_splats_views_and_splat_relevance_over_the_link(served, monkeypatch):
    from olsplat_nodes.nodes import query_server as server_module
    from olsplat_nodes.query.answer import QueryFeatures, encoder_for_map
    from olsplat_nodes.query.splats import browser_splats, pack_splats, relevance_margin
    from olsplat_nodes.scene import read_ply
    from olsplat_nodes.storage import LanguageMap, latest_map, load_views

    scene, run, client = served
    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    splats = client.request(SplatsRequest(request_id="p", max_splats=5000))
    assert isinstance(splats, SplatsReply) and splats.status == "ok" and splats.total == len(gaussians)
    expected = pack_splats(browser_splats(gaussians, 5000))
    for name, array in expected.items():
        np.testing.assert_array_equal(getattr(splats, name), array, err_msg=name)
    assert "5,000 of" in splats.message
    for bad in (0, 500_001):
        refused = client.request(SplatsRequest(request_id="b", max_splats=bad))
        assert refused.status == "bad_request" and "max_splats must be 1..500,000" in refused.message
        assert refused.centers is None

    # views in pages (a page of 3 here, 500 in service): every camera once, in order
    monkeypatch.setattr(server_module, "VIEWS_PER_REPLY", 3)
    views = load_views(run / "views")
    got: list = []
    while True:
        page = client.request(ViewsRequest(request_id="v", start=len(got)))
        assert isinstance(page, ViewsReply) and page.total == len(views) and page.start == len(got)
        if not page.views:
            break
        assert len(page.views) <= 3
        got += page.views
    assert [v["name"] for v in got] == [v.camera.name for v in views]
    for record, view in zip(got, views, strict=True):
        np.testing.assert_array_equal(np.reshape(record["K"], (3, 3)), view.camera.K)
        np.testing.assert_array_equal(np.reshape(record["world_from_camera"], (4, 4)), view.camera.world_from_camera)
        assert (record["width"], record["height"]) == (view.camera.width, view.camera.height)

    # a query's relevance per splat, in the SplatsReply's order
    negatives = ["road", "trees"]
    reply = client.request(QueryRequest(request_id="q", text="red roof buildings", negatives=negatives, splats=5000))
    assert reply.status == "ok" and reply.splat_margin.dtype == np.float16 and len(reply.splat_margin) == 5000
    language_map = LanguageMap.load(latest_map(run / "map")["path"], decode=False)
    texts = encoder_for_map(language_map).encode_text(["red roof buildings", *negatives])
    ids = browser_splats(gaussians, 5000).ids
    margin = relevance_margin(QueryFeatures.of(language_map), language_map.observed, ids, texts)
    np.testing.assert_array_equal(np.isnan(reply.splat_margin), ~language_map.observed[ids])
    np.testing.assert_array_equal(reply.splat_margin, margin.astype(np.float16))
    assert client.request(QueryRequest(request_id="n", text="road")).splat_margin is None  # not asked: not sent
    too_many = client.request(QueryRequest(request_id="t", text="road", splats=600_000))
    assert too_many.status == "bad_request" and "splats must be 0..500,000" in too_many.message

    own = client.request(StatusRequest(request_id="s")).nodes[0]["values"]
    record = latest_map(run / "map")
    assert own["map_version"] == record["version"] and own["map_views"] == record["views"]
    assert own["map_final"] == int(record["final"]) and own["map_observed"] == int(language_map.observed.sum())


def test_the_pages_link_source_shows_the_drones_map_views_and_answers(served):
    from olsplat_nodes.ground.link import LinkSource
    from olsplat_nodes.storage import latest_map, load_views

    _, run, client = served
    source = LinkSource(client, 4000)
    assert source.status_rows()[0][1] == "ERROR" and "connecting" in source.status_rows()[0][2]
    assert source.refresh() is True
    assert len(source.splats.centers) == 4000 and source.splats.total > 4000
    assert source.state.version == latest_map(run / "map")["version"] and source.state.final
    assert [c.name for c in source.cameras()] == [v.camera.name for v in load_views(run / "views")]
    rows = {what: (level, text) for what, level, text in source.status_rows()}
    assert rows["link"][0] == "OK" and "no encryption" in rows["link"][1]
    assert rows["map"][0] == "OK" and "final (the flight ended)" in rows["map"][1]
    assert rows["query_server"][0] == "OK"
    assert source.refresh() is False  # nothing new

    answer = source.ask("parking lot", ["road", "trees"], ENCODE_VIEW)  # in the view's annotation (no red roofs)
    assert answer.status == "ok", answer.message
    assert answer.margin.shape == (4000,) and np.isfinite(answer.margin).any()
    assert answer.instances and all(i.gaussians >= 20 for i in answer.instances)
    assert answer.heatmap_picture.shape[1] == 320 and answer.mask_picture.shape == answer.heatmap_picture.shape
    assert source.ask("roof\x07", [], "").status == "bad_request"
    assert source.ask("x" * 10_000, [], "").message.startswith("the query is 10,000 characters")


def test_a_silent_link_is_a_state_the_page_shows_not_an_error(ctx, sockdir):
    from olsplat_nodes.ground.link import LinkSource

    with QueryClient(ctx, f"ipc://{sockdir}/nobody.sock", timeout_s=0.3) as client:
        source = LinkSource(client, 1000)
        assert source.refresh() is False
        level, text = {w: (lv, t) for w, lv, t in source.status_rows()}["link"]
        assert level == "ERROR" and text.startswith("link lost - retrying") and "0.3 s" in text
        answer = source.ask("road", [], "")
        assert answer.status == "no_map" and "not come from the drone" in answer.message
        source.splats = object()  # as if the map had come before the link went silent
        answer = source.ask("road", [], "")
        assert answer.status == "timeout" and "link lost" in answer.message


def test_a_drone_speaking_another_wire_version_is_named_as_such(ctx, sockdir):
    """A server of another schema version answers, but in a form this client refuses: the page
    says so instead of calling the link lost."""
    import threading

    import msgpack
    import zmq

    from olsplat_msgs import StatusReply, encode
    from olsplat_nodes.ground.link import LinkSource

    endpoint = f"ipc://{sockdir}/other.sock"
    router = ctx.socket(zmq.ROUTER)
    router.linger = 0
    router.bind(endpoint)

    def other_version_server():
        if router.poll(5000):
            identity, _empty, *_request = router.recv_multipart()
            topic, header, *arrays = encode(StatusReply(request_id="x"), "query")
            later = msgpack.packb({**msgpack.unpackb(header), "version": 99})
            router.send_multipart([identity, b"", topic, later, *arrays])

    thread = threading.Thread(target=other_version_server, daemon=True)
    thread.start()
    try:
        with QueryClient(ctx, endpoint, timeout_s=1.0) as client:
            source = LinkSource(client, 1000)
            assert source.refresh() is False
            level, text = {w: (lv, t) for w, lv, t in source.status_rows()}["link"]
            assert level == "ERROR" and "cannot read" in text and "another olsplat version" in text
    finally:
        thread.join(5)
        router.close()


def test_a_nodes_error_reaches_the_status_panel_with_its_message(ctx, sockdir):
    """The status panel's rows of nodes as the query server reports them (a field launch whose
    camera is missing: the ingest's ERROR and its message)."""
    from olsplat_nodes.ground.link import LinkSource, node_row

    ingest = {
        "node": "ingest",
        "level": 2,
        "message": "camera /dev/video0: no such device",
        "values": {"rate_hz": 0.0, "latency_ms": 0.0, "dropped": 1, "gaps": 2},
        "age_s": 0.4,
    }
    name, level, text = node_row(ingest)
    assert (name, level) == ("ingest", "ERROR")
    assert text.startswith("camera /dev/video0: no such device;") and "drops 3" in text
    assert node_row({**ingest, "level": 3})[1] == "STALE" and node_row({**ingest, "level": 1})[1] == "WARN"

    # the link goes silent after that status: the last rows heard stay, marked STALE
    with QueryClient(ctx, f"ipc://{sockdir}/gone.sock", timeout_s=0.3) as client:
        source = LinkSource(client, 100)
        source.nodes = [ingest]
        source.refresh()
        rows = {what: (level, text) for what, level, text in source.status_rows()}
    assert rows["ingest"][0] == "STALE" and rows["ingest"][1].startswith("last heard: camera /dev/video0")
