"""Garbage, truncated, oversized and wrong-version messages on every receiving socket of every
node: counted (in the node's DiagnosticStatus heartbeats, or the query server's own status),
dropped, and the node keeps serving: the valid message that follows is handled.

Each node runs for real in a thread on real sockets; the test owns the sockets at the other end
(a PUB bound where the node's SUB connects, a PUB connecting to the query server's bound
collector, raw DEALERs for its ROUTER). A valid message is sent first until the node has
handled one (ZeroMQ's slow joiner: what is sent before the subscription is in place is lost
and never counted), then every bad kind once, then a valid message. The oversized message is
one frame over the nodes' real limit (256 MiB): libzmq refuses it from its size header and
drops that connection; the node's subscriber connects again (counted as ``reconnects``).
"""

from __future__ import annotations

import dataclasses
import time

import pytest
import zmq

from olsplat_msgs import (
    DiagnosticStatus,
    EndOfStream,
    ImageFrame,
    MapUpdated,
    ObservationsAdded,
    QueryReply,
    QueryRequest,
    RegionFeatures,
    StatusReply,
    StatusRequest,
    decode,
    encode,
)
from olsplat_nodes.method import read_manifest
from olsplat_nodes.scene import read_ply
from olsplat_nodes.transport import CONTROL_MAX_BYTES, QueryClient
from tests.helpers import every, wait_for

from .conftest import (
    Heartbeats,
    NodeThread,
    Tap,
    accumulator_params,
    bad_variants,
    image_frame,
    oversized,
    query_server,
    raw_socket,
    refiner,
    send,
    send_msg,
)

pytestmark = pytest.mark.timeout(120)


def send_all_bad(pub: zmq.Socket, good: list[bytes], *more_bad) -> int:
    """Every corruption of ``good`` and the extra bad messages (valid on the wire, but of the
    wrong type or inconsistent), once each; returns how many were sent."""
    variants = list(bad_variants(good).values())
    for frames in variants:
        send(pub, frames)
    for frames in more_bad:
        send(pub, frames)
    return len(variants) + len(more_bad)


# ---------------------------------------------------------------------------------------------
# accumulator: regions_in


def test_accumulator_counts_bad_regions_and_still_adds_the_valid_view(
    ctx, sockdir, tmp_path, tiny, tiny_camera, region_features
):
    from olsplat_nodes.nodes.accumulator import AccumulatorNode
    from olsplat_nodes.storage import ObservationStore

    scene, _ = tiny
    regions = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/regions.sock", bind=True)
    beats = Heartbeats(ctx)
    observations = Tap(ctx, f"ipc://{sockdir}/observations.sock", ["observations"])
    node = AccumulatorNode("accumulator", accumulator_params(scene, tmp_path, sockdir, beats))
    try:
        with NodeThread(node) as running:
            # in sync once an EndOfStream comes back on the observations topic
            wait_for(
                lambda: observations.got(EndOfStream),
                20,
                "the accumulator to forward EndOfStream",
                step=every(0.1, lambda: send_msg(regions, EndOfStream(frame_id="sync", source="test"), "regions")),
            )

            good = encode(region_features, "regions")
            wrong_type = encode(image_frame(*tiny_camera), "regions")  # an ImageFrame on `regions`
            inconsistent = encode(
                dataclasses.replace(region_features, name="inconsistent", width=321), "regions"
            )  # labels 320 wide
            bad = send_all_bad(regions, good, wrong_type, inconsistent)
            send(regions, good)

            added = wait_for(lambda: observations.got(ObservationsAdded), 30, "ObservationsAdded for the valid view")
            ack = added[0]
            assert (
                ack.name == region_features.name
                and not ack.duplicate
                and ack.views_in_store == 1
                and ack.observations > 0
            )
            values = beats.wait("accumulator", lambda v: v.get("bad_messages", 0) >= bad, 10, f"bad_messages >= {bad}")
            assert values["bad_messages"] == bad, values
            running.assert_running()

            # one frame over the size limit: the connection is dropped and made again; the view
            # sent again afterwards is acknowledged (as a duplicate: never added twice)
            send(regions, oversized("regions", 160 * 2**20))  # the accumulator's default max_message_mb
            wait_for(
                lambda: len(observations.got(ObservationsAdded)) >= 2,
                20,
                "an acknowledgement after the oversized message",
                step=every(0.2, lambda: send(regions, good)),
            )
            assert observations.of_type(ObservationsAdded)[-1].duplicate
            values = beats.wait("accumulator", lambda v: v.get("reconnects", 0) >= 1, 10, "reconnects >= 1")
            assert values["bad_messages"] == bad
            running.assert_running()

            # well formed, but its features are narrower than the store's: stored, it would make
            # every later refinement fail; it is refused and counted
            narrow = dataclasses.replace(region_features, name="narrow", features=region_features.features[:, :8])
            send(regions, encode(narrow, "regions"))
            values = beats.wait("accumulator", lambda v: v.get("bad_messages", 0) > bad, 10, "the narrow view counted")
            assert values["bad_messages"] == bad + 1
            running.assert_running()
        store = ObservationStore(tmp_path / "store", len(read_ply(scene / "map" / "point_cloud.ply")))
        assert store.names() == [region_features.name]
        manifest = read_manifest(tmp_path / "store")
        assert manifest is not None and manifest.feature_dim == region_features.features.shape[1]
        features, observed = store.refine(None, manifest.method.aggregation)
        assert observed.any() and features.shape[1] == manifest.feature_dim
        assert observations.undecodable == []
    finally:
        for sock in (regions, beats, observations):
            sock.close()


# ---------------------------------------------------------------------------------------------
# region encoder: frames_in


def test_region_encoder_counts_bad_frames_and_still_encodes_the_valid_one(ctx, sockdir, tiny_camera):
    from olsplat_nodes.nodes.region_encoder import RegionEncoderNode

    camera, image = tiny_camera
    frames = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/frames.sock", bind=True)
    beats = Heartbeats(ctx)
    regions = Tap(ctx, f"ipc://{sockdir}/regions.sock", ["regions"])
    node = RegionEncoderNode(
        "region_encoder",
        {
            "latest_wins": False,  # every frame in order: the inconsistent frame must be looked at, not skipped
            "frames_in": f"ipc://{sockdir}/frames.sock",
            "regions_out": f"ipc://{sockdir}/regions.sock",
            "diagnostics": beats.endpoint,
        },
    )
    try:
        with NodeThread(node) as running:
            wait_for(
                lambda: regions.got(EndOfStream),
                20,
                "the encoder to forward EndOfStream",
                step=every(0.1, lambda: send_msg(frames, EndOfStream(frame_id="sync", source="test"), "frames")),
            )

            good = encode(image_frame(camera, image, seq=1, name="good.jpg"), "frames")
            wrong_type = encode(ObservationsAdded(name="x"), "frames")
            inconsistent = encode(
                image_frame(camera, image[:, :300].copy(), seq=2, name="cropped.jpg"), "frames"
            )  # 300 wide, camera says 320
            bad = send_all_bad(frames, good, wrong_type, inconsistent)
            send(frames, good)

            out = wait_for(lambda: regions.got(RegionFeatures), 30, "RegionFeatures for the valid frame")
            assert [m.name for m in out] == ["good.jpg"]
            assert out[0].label_maps.shape[1:] == (240, 320) and len(out[0].features) == out[0].level_sizes.sum()
            values = beats.wait(
                "region_encoder", lambda v: v.get("bad_messages", 0) >= bad, 10, f"bad_messages >= {bad}"
            )
            assert values["bad_messages"] == bad, values
            running.assert_running()

            send(frames, oversized("frames", 64 * 2**20))  # the region encoder's default max_message_mb
            wait_for(
                lambda: len(regions.got(RegionFeatures)) >= 2,
                20,
                "RegionFeatures after the oversized message",
                step=every(0.2, lambda: send(frames, good)),
            )  # answered from the node's cache of recent results
            values = beats.wait("region_encoder", lambda v: v.get("reconnects", 0) >= 1, 10, "reconnects >= 1")
            assert values["bad_messages"] == bad
            running.assert_running()
        assert regions.undecodable == []
    finally:
        for sock in (frames, beats, regions):
            sock.close()


# ---------------------------------------------------------------------------------------------
# refiner: observations_in


def test_refiner_counts_bad_observations_and_still_writes_the_final_map(ctx, sockdir, tmp_path, tiny, tiny_run):
    import shutil

    from olsplat_nodes.storage import latest_map

    scene, _ = tiny
    shutil.copytree(tiny_run / "store", tmp_path / "store")  # one view, as the accumulator left it
    observations = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/observations.sock", bind=True)
    beats = Heartbeats(ctx)
    maps = Tap(ctx, f"ipc://{sockdir}/map.sock", ["map"])
    node = refiner(scene, sockdir, tmp_path / "store", tmp_path / "map", beats.endpoint)
    seq = iter(range(1, 10_000))

    def ack():
        send_msg(
            observations,
            ObservationsAdded(seq=next(seq), frame_id="camera", name="frame_0003.jpg", views_in_store=1),
            "observations",
        )

    try:
        with NodeThread(node) as running:
            beats.wait(
                "refiner", lambda v: v.get("received", 0) >= 1, 20, "received >= 1 (in sync)", step=every(0.1, ack)
            )

            good = encode(ObservationsAdded(seq=5000, frame_id="camera", name="frame_0003.jpg"), "observations")
            wrong_type = encode(MapUpdated(version=9, path="/nowhere"), "observations")
            bad = send_all_bad(observations, good, wrong_type)
            values = beats.wait("refiner", lambda v: v.get("bad_messages", 0) >= bad, 10, f"bad_messages >= {bad}")
            assert values["bad_messages"] == bad, values

            send(observations, oversized("observations", CONTROL_MAX_BYTES))
            beats.wait(
                "refiner",
                lambda v: v.get("reconnects", 0) >= 1 and v.get("received", 0) > values["received"],
                20,
                "a reconnect and a valid message after it",
                step=every(0.1, ack),
            )
            running.assert_running()

            # the valid end of the stream: one final pass, MapUpdated(final) and exit 0
            wait_for(
                lambda: any(m.final for m in maps.got(MapUpdated)),
                30,
                "the final MapUpdated",
                step=every(
                    0.3,
                    lambda: send_msg(
                        observations, EndOfStream(seq=1, frame_id="camera", source="test", frames=1), "observations"
                    ),
                ),
            )
            assert running.join(10) == 0
        record = latest_map(tmp_path / "map")
        assert record["final"] and record["views"] == 1 and record["version"] == 1
        final = maps.of_type(MapUpdated)[-1]
        assert final.version == 1 and final.path == record["path"] and final.observed_gaussians > 0
        stopping = beats.wait("refiner", lambda v: v.get("map_version") == 1, 5, "the stopping heartbeat")
        assert stopping["bad_messages"] == bad
    finally:
        for sock in (observations, beats, maps):
            sock.close()


# ---------------------------------------------------------------------------------------------
# ingest: acks_in and map_in (one SUB connected to both)


def test_ingest_counts_bad_acks_and_map_announcements_and_still_delivers_every_frame(ctx, sockdir, tmp_path, tiny):
    from olsplat_nodes.nodes.ingest import IngestNode

    scene, summary = tiny
    acks = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/acks.sock", bind=True)
    maps = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/map.sock", bind=True)
    beats = Heartbeats(ctx)
    frames = Tap(ctx, f"ipc://{sockdir}/frames.sock", ["frames"])
    node = IngestNode(
        "ingest",
        {
            "source": str(scene / "replay.mcap"),
            "fast": True,
            "window": 2,
            "ack_timeout_s": 0.5,  # unacknowledged frames come again soon
            "frames_out": f"ipc://{sockdir}/frames.sock",
            "acks_in": f"ipc://{sockdir}/acks.sock",
            "map_in": f"ipc://{sockdir}/map.sock",
            "state_file": str(tmp_path / "acknowledged.txt"),
            "diagnostics": beats.endpoint,
        },
    )
    seqs = {"ack": iter(range(1, 100_000)), "map": iter(range(1, 100_000))}

    def ack_all():  # acknowledge every frame seen so far, as the accumulator would
        for name in sorted({m.name for m in frames.got(ImageFrame, 0)}):
            send_msg(acks, ObservationsAdded(seq=next(seqs["ack"]), frame_id="camera", name=name), "observations")

    def announce(final=False):
        send_msg(maps, MapUpdated(seq=next(seqs["map"]), frame_id="map", version=1, path="/m.npz", final=final), "map")

    try:
        with NodeThread(node) as running:
            # acks link in sync: a frame was acknowledged; then the map link: a MapUpdated arrived
            beats.wait(
                "ingest",
                lambda v: v.get("acknowledged", 0) >= 1,
                20,
                "a first acknowledgement",
                step=every(0.2, ack_all),
            )
            received = beats.wait("ingest", lambda v: True, 5, "a heartbeat")["received"]
            beats.wait(
                "ingest", lambda v: v.get("received", 0) > received + 1, 20, "a MapUpdated", step=every(0.1, announce)
            )

            bad = send_all_bad(
                acks,
                encode(ObservationsAdded(seq=90_000, name="frame_0000.jpg"), "observations"),
                encode(StatusRequest(request_id="x"), "observations"),
            )
            bad += send_all_bad(
                maps,
                encode(MapUpdated(seq=90_000, version=7, path="/m.npz"), "map"),
                encode(StatusRequest(request_id="y"), "map"),
            )
            values = beats.wait("ingest", lambda v: v.get("bad_messages", 0) >= bad, 10, f"bad_messages >= {bad}")
            assert values["bad_messages"] == bad, values
            running.assert_running()

            # one oversized frame on each link: both connections are made again
            send(acks, oversized("observations", CONTROL_MAX_BYTES))
            send(maps, oversized("map", CONTROL_MAX_BYTES))
            beats.wait("ingest", lambda v: v.get("reconnects", 0) >= 2, 20, "reconnects >= 2", step=every(0.2, ack_all))

            # valid acknowledgements: every frame is delivered; then the final map ends the node with 0
            beats.wait(
                "ingest",
                lambda v: v.get("acknowledged", 0) == summary["views"] and v.get("in_flight") == 0,
                30,
                "every frame acknowledged",
                step=every(0.2, ack_all),
            )
            wait_for(lambda: frames.got(EndOfStream), 10, "EndOfStream after the last frame")
            wait_for(
                lambda: not running.running,
                10,
                "ingest to exit after the final map",
                step=every(0.2, lambda: announce(final=True)),
            )
            assert running.join(5) == 0
        assert (
            sorted({m.name for m in frames.of_type(ImageFrame)})
            == frames.of_type(EndOfStream)[-1].names
            == sorted((tmp_path / "acknowledged.txt").read_text().split())
        )
        final = beats.wait("ingest", lambda v: v.get("acknowledged") == summary["views"], 5, "the last heartbeat")
        assert final["bad_messages"] == bad
    finally:
        for sock in (acks, maps, beats, frames):
            sock.close()


# ---------------------------------------------------------------------------------------------
# query server: the ROUTER (query link), the bound diagnostics collector, and map_in


def _status(endpoint: str, ctx) -> StatusReply:
    with QueryClient(ctx, endpoint, timeout_s=5.0) as client:
        reply = client.request(StatusRequest())
    assert isinstance(reply, StatusReply)
    return reply


def _own(reply: StatusReply, name: str = "query_server") -> dict:
    return next(n for n in reply.nodes if n["node"] == name)["values"]


def _replies(dealer: zmq.Socket, count: int, timeout_s: float) -> list:
    """The next ``count`` replies on a raw DEALER (each ``["", topic, header, ...]``), decoded."""
    replies = []
    deadline = time.monotonic() + timeout_s
    while len(replies) < count:
        if not dealer.poll(max(1, int((deadline - time.monotonic()) * 1000))):
            pytest.fail(f"got {len(replies)} of {count} replies within {timeout_s} s")
        frames = dealer.recv_multipart()
        assert frames[0] == b""
        replies.append(decode(frames[1:])[1])
    return replies


def test_query_server_answers_bad_requests_counts_bad_input_on_every_socket_and_keeps_serving(
    ctx, sockdir, tmp_path, tiny, tiny_run
):
    import shutil

    scene, _ = tiny
    query = f"ipc://{sockdir}/query.sock"
    maps = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/map.sock", bind=True)
    node = query_server(scene, sockdir, tmp_path / "map", tiny_run / "views")
    dealer = heartbeat = None
    try:
        with NodeThread(node) as running:
            assert _status(query, ctx).map_version == 0

            # -- the query link: every bad request is answered with bad_request, one reply each
            dealer = raw_socket(ctx, zmq.DEALER, query, bind=False)
            good = encode(QueryRequest(request_id="bad", text="road"), "query")
            bad_requests = [[b"", *frames] for frames in bad_variants(good).values()]
            bad_requests += [
                good,  # no empty delimiter frame (a DEALER must send it)
                [b"not empty", *good],
                [b"", *encode(MapUpdated(version=1), "query")],  # valid, but not a request
                [b""],
            ]
            for frames in bad_requests:
                send(dealer, frames)
            replies = _replies(dealer, len(bad_requests), timeout_s=10)
            assert {r.status for r in replies} == {"bad_request"} and all(
                isinstance(r, QueryReply) and r.message for r in replies
            )
            send(dealer, [b"", *encode(QueryRequest(request_id="fine", text="road"), "query")])
            [answer] = _replies(dealer, 1, timeout_s=5)
            assert answer.request_id == "fine" and answer.status == "no_map"
            assert _own(_status(query, ctx))["bad_requests"] == len(bad_requests)

            # an oversized request: libzmq drops that client's connection; nobody else notices
            send(dealer, [b"", b"query", zmq.Frame(bytes(257 * 2**20))])
            assert not dealer.poll(500)
            assert _status(query, ctx).map_version == 0
            running.assert_running()

            # -- the diagnostics collector (bound): a heartbeat PUB that sends garbage
            heartbeat = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/diagnostics.sock", bind=False)
            seq = iter(range(1, 10_000))

            def beat(node_name="probe"):
                send_msg(
                    heartbeat,
                    DiagnosticStatus(seq=next(seq), frame_id=node_name, node=node_name, message="fine"),
                    "diagnostics",
                )

            wait_for(
                lambda: "probe" in [n["node"] for n in _status(query, ctx).nodes],
                10,
                "the probe's heartbeat",
                step=every(0.1, beat),
            )
            before = _own(_status(query, ctx))
            collector_bad = send_all_bad(
                heartbeat,
                encode(DiagnosticStatus(seq=9000, node="bad"), "diagnostics"),
                encode(StatusRequest(), "diagnostics"),
            )
            beat("after")
            wait_for(
                lambda: "after" in [n["node"] for n in _status(query, ctx).nodes],
                10,
                "the heartbeat after the bad ones",
            )
            values = _own(_status(query, ctx))
            assert (
                values["diagnostics_bad_messages"] - before["diagnostics_bad_messages"] == collector_bad - 1
            )  # the StatusRequest decodes:
            assert values["bad_messages"] - before["bad_messages"] == collector_bad  # the node counts that one
            assert "bad" not in [n["node"] for n in _status(query, ctx).nodes]

            # -- map_in: garbage on the map topic, then the real snapshot and its announcement
            def announce():
                send_msg(
                    maps,
                    MapUpdated(seq=next(seq), frame_id="map", version=1, path=str(tmp_path / "map"), views=1),
                    "map",
                )

            wait_for(
                lambda: _own(_status(query, ctx))["map_received"] >= 1, 10, "a MapUpdated", step=every(0.1, announce)
            )
            before = _own(_status(query, ctx))
            map_bad = send_all_bad(maps, encode(MapUpdated(seq=9000, version=5), "map"), encode(StatusRequest(), "map"))
            send(maps, oversized("map", CONTROL_MAX_BYTES))
            shutil.copytree(tiny_run / "map", tmp_path / "staging")
            (tmp_path / "staging").rename(tmp_path / "map")  # appears at once, as the refiner's atomic writes do
            wait_for(
                lambda: _status(query, ctx).map_version == 1, 10, "the map to be loaded", step=every(0.2, announce)
            )
            wait_for(
                lambda: _own(_status(query, ctx))["map_reconnects"] >= 1,
                10,
                "a reconnect on map_in",
                step=every(0.2, announce),
            )
            values = _own(_status(query, ctx))
            assert values["bad_messages"] - before["bad_messages"] == map_bad
            assert values["map_bad_messages"] - before["map_bad_messages"] == map_bad - 1
            assert values["bad_messages"] == len(bad_requests) + collector_bad + map_bad

            with QueryClient(ctx, query, timeout_s=30.0) as client:
                # against the aerial vocabulary the tiny town's one red roof is too small for an instance
                reply = client.request(QueryRequest(text="parking lot"))
            assert reply.status == "ok" and reply.map_version == 1 and any(i["kind"] == "3d" for i in reply.instances)
            running.assert_running()
    finally:
        for sock in (maps, dealer, heartbeat):
            if sock is not None:
                sock.close()


# ---------------------------------------------------------------------------------------------
# regression: the subscriber's reconnect after an oversized frame


def test_a_subscriber_reconnecting_after_an_oversized_frame_does_not_abort_the_process(sockdir):
    """Messages queued ahead of the oversized frame that made libzmq cut the connection: the
    subscriber used to disconnect the endpoint while libzmq held the first frame of the next one
    (polling prefetches it), which aborts the whole process (``Assertion failed: !_more
    (src/fq.cpp:80)``). Run in a child process so that a regression fails this test only."""
    import json
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(f"""
        import json, time, zmq
        from olsplat_msgs import EndOfStream, encode
        from olsplat_nodes.transport import Subscriber
        ctx = zmq.Context()
        pub = ctx.socket(zmq.PUB); pub.linger = 0; pub.sndhwm = 10000
        pub.bind("ipc://{sockdir}/regression.sock")
        sub = Subscriber(ctx, "ipc://{sockdir}/regression.sock", ["t"], hwm=1000, max_bytes=1 << 16)
        while sub.recv(50) is None:
            pub.send_multipart(encode(EndOfStream(frame_id="sync"), "t"))
        for seq in range(1, 13):
            pub.send_multipart(encode(EndOfStream(seq=seq, frame_id="queued"), "t"))
        pub.send_multipart([b"t", b"x", bytes(1 << 17)])  # over max_bytes: libzmq cuts the connection
        time.sleep(0.2)  # not a wait for a result: lets the disconnect be reported while the 12 are queued
        queued = [m.seq for _, m in sub.drain(1000) if m.frame_id == "queued"]
        deadline = time.monotonic() + 10
        after = None
        while after is None and time.monotonic() < deadline:  # the stream comes back
            pub.send_multipart(encode(EndOfStream(seq=99, frame_id="after"), "t"))
            after = next((m for _, m in sub.drain(100) if m.frame_id == "after"), None)
        print(json.dumps({{"queued": queued, "after": after is not None, "reconnects": sub.stats["reconnects"]}}))
        sub.close(); pub.close(); ctx.term()
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert result == {"queued": list(range(1, 13)), "after": True, "reconnects": 1}  # nothing queued was lost either
