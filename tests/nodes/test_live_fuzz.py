"""The running graph under a structure-aware fuzzer: ``OLSPLAT_FUZZ_PER_SOCKET`` (default
10,000) mutated messages to every input of every node, then the normal flight. No node dies,
every bad message is counted by the node that received it, and the final map is the map of
a clean run. Seed fixed here (``OLSPLAT_FUZZ_SEED``); ``make fuzz`` runs 100,000 per socket with
a fresh seed, printed. See ``livefuzz.py`` for the mutators, the oracle and the gate proxies."""

from __future__ import annotations

import os
import time

import numpy as np
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
    StatusRequest,
    decode,
    encode,
)
from olsplat_nodes.launcher import Supervisor
from olsplat_nodes.scene import Camera, intrinsics, look_at
from olsplat_nodes.storage import LanguageMap, ObservationStore, latest_map
from olsplat_nodes.transport import CONTROL_MAX_BYTES, REQUEST_MAX_BYTES, QueryClient
from olsplat_nodes.transport.convert import camera_of, view_of
from tests.helpers import free_port, wait_for

from .conftest import Background, launch_tiny, pid_of
from .livefuzz import GateProxy, Mutator, Oracle, bad_messages

PER_SOCKET = int(os.environ.get("OLSPLAT_FUZZ_PER_SOCKET", "10000"))
SEED = int(os.environ.get("OLSPLAT_FUZZ_SEED", "20261123"))
NODES = ("ingest", "region_encoder", "accumulator", "refiner", "query_server")


def _templates(encoder: str, dim: int) -> dict[str, list[list[bytes]]]:
    """Small valid messages of every kind, by topic (16x12 pixels: mutants stay cheap)."""
    camera = Camera("fuzz.jpg", 16, 12, intrinsics(14.0, 14.0, 8.0, 6.0), look_at([0, -5, 5], [0, 0, 0], (0, 0, 1)))
    image = np.random.default_rng(0).integers(0, 255, (12, 16, 3), dtype=np.uint8)
    frame = ImageFrame(
        seq=1, frame_id="camera", name="fuzz.jpg", image=image, K=camera.K, D=np.zeros(0), distortion_model="none",
        world_from_camera=camera.world_from_camera, width=16, height=12,
    )  # fmt: skip
    labels = np.where(np.arange(16)[None, None, :] < 8, 0, 1).repeat(12, axis=1).astype(np.int32)
    labels[0, 0, 0] = -1
    regions = RegionFeatures(
        seq=1, frame_id="camera", name="fuzz.jpg", source_seq=1, encoder=encoder, label_maps=labels,
        level_sizes=np.array([2], np.int32), features=np.eye(2, dim, dtype=np.float16), image=image,
        K=camera.K, D=np.zeros(0), distortion_model="none", world_from_camera=camera.world_from_camera,
        width=16, height=12,
    )  # fmt: skip
    return {
        "frames": [encode(frame, "frames"), encode(EndOfStream(seq=1, frame_id="camera", frames=3), "frames")],
        "regions": [encode(regions, "regions"), encode(EndOfStream(seq=1, frame_id="camera"), "regions")],
        "observations": [
            encode(ObservationsAdded(seq=1, frame_id="camera", name="fuzz.jpg", views_in_store=1), "observations"),
            encode(EndOfStream(seq=1, frame_id="camera", frames=1), "observations"),
        ],
        "map": [encode(MapUpdated(seq=1, frame_id="map", version=1, path="/nowhere/m.npz", views=1), "map")],
        "diagnostics": [
            encode(DiagnosticStatus(seq=1, node="fuzz", level=0, message="ok", values={"rate_hz": 1.0}), "diagnostics")
        ],
        "query": [
            encode(QueryRequest(request_id="f", text="road", view="frame_0001.jpg", negatives=["trees"]), "query"),
            encode(StatusRequest(request_id="s"), "query"),
        ],
    }


def _query_content(message: QueryRequest) -> None:
    """The query server's own limits (max_text_chars 200, max_negatives 32)."""
    if not message.text.strip() or len(message.text) > 200 or len(message.negatives) > 32:
        raise ValueError("refused")
    if any(len(n) > 200 for n in message.negatives):
        raise ValueError("refused")


def _oracles() -> dict[str, Oracle]:
    """Per link: the union of what its downstream nodes accept (a mutant must be refused by all)."""
    control = {ObservationsAdded: None, EndOfStream: None, MapUpdated: None}  # the ingest takes all three on both
    return {
        "frames": Oracle({ImageFrame: camera_of, EndOfStream: None}, 64 * 2**20),
        "regions": Oracle({RegionFeatures: lambda m: view_of(m, None, None, None), EndOfStream: None}, 160 * 2**20),
        "observations": Oracle(control, CONTROL_MAX_BYTES),
        "map": Oracle(control, CONTROL_MAX_BYTES),
        "diagnostics": Oracle({DiagnosticStatus: None}, CONTROL_MAX_BYTES),
        "query": Oracle({QueryRequest: _query_content, StatusRequest: None}, REQUEST_MAX_BYTES),
    }


def _bad_counts(client: QueryClient) -> dict[str, int]:
    reply = client.request(StatusRequest(request_id="fuzz"))
    return {n["node"]: int(n["values"].get("bad_messages", 0)) for n in reply.nodes if n["node"] in NODES}


def _settled(client: QueryClient, want: dict[str, int], timeout_s: float) -> dict[str, int]:
    """The nodes' bad_messages once every one has reached ``want`` and two reads agree."""
    deadline = time.monotonic() + timeout_s
    last: dict[str, int] = {}
    while time.monotonic() < deadline:
        counts = _bad_counts(client)
        if all(counts.get(n, -1) >= v for n, v in want.items()) and counts == last:
            return counts
        last = counts
        time.sleep(1.5)
    raise AssertionError(f"bad_messages {last}, expected at least {want}")


@pytest.mark.timeout(1800)
def test_the_fuzzed_graph_counts_every_bad_message_loses_no_node_and_makes_the_clean_map(
    tiny,
    tmp_path,
    offline_map,
):
    from olsplat_nodes.encoders.spec import encoder_from_spec

    scene, summary = tiny
    run_dir, port = tmp_path / "run", free_port()
    links = {  # link -> (the upstream node's socket under run_dir, the parameters of its readers, pointed at the proxy)
        "frames": ("frames", ["region_encoder.frames_in"]),
        "regions": ("regions", ["accumulator.regions_in"]),
        "observations": ("observations", ["refiner.observations_in", "ingest.acks_in"]),
        "map": ("map", ["ingest.map_in", "query_server.map_in"]),
    }
    overrides = ["query_server.queries_per_s=0"]  # the flood is the point here, not the rate limit
    for name, (_, readers) in links.items():
        overrides += [f"{reader}=ipc://{run_dir}/fuzz_{name}.sock" for reader in readers]
    config = launch_tiny(scene, run_dir, port, *overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    ctx = zmq.Context.instance()
    proxies = {
        name: GateProxy(ctx, f"ipc://{run_dir}/{sock}.sock", f"ipc://{run_dir}/fuzz_{name}.sock")
        for name, (sock, _) in links.items()
    }
    supervisor = Supervisor(config)
    running = Background(supervisor)
    client = QueryClient(ctx, f"tcp://127.0.0.1:{port}", timeout_s=30.0)
    diag = ctx.socket(zmq.XPUB)  # the collector is bound by the query server: connect to it, no drops
    diag.linger = 0
    diag.setsockopt(zmq.XPUB_NODROP, 1)
    diag.connect(f"ipc://{run_dir}/diagnostics.sock")
    dealer = ctx.socket(zmq.DEALER)
    dealer.linger = 0
    dealer.connect(f"tcp://127.0.0.1:{port}")
    downstream = {
        "frames": ["region_encoder"],
        "regions": ["accumulator"],
        "observations": ["refiner", "ingest"],
        "map": ["ingest", "query_server"],
        "diagnostics": ["query_server"],
    }
    try:
        wait_for(lambda: set(_bad_counts(client)) == set(NODES), 120, "every node's heartbeat")
        pids = {node: pid_of(supervisor, node) for node in NODES}

        # in sync: a garbage message on every link until each node behind it has counted one
        def probe():
            for name, proxy in proxies.items():
                proxy.inject([name.encode(), b"\xc1"])
            send_blocking(diag, [b"diagnostics", b"\xc1"])

        wanted = {node: 1 for nodes in downstream.values() for node in nodes}
        step_at = [0.0]

        def synced():
            if time.monotonic() - step_at[0] > 0.5:
                probe()
                step_at[0] = time.monotonic()
            counts = _bad_counts(client)
            return all(counts.get(n, 0) >= v for n, v in wanted.items())

        wait_for(synced, 60, "every node to count a probe")
        for proxy in proxies.values():
            proxy.wait_sent()
        baseline = _settled(client, wanted, 30)

        templates = _templates(encoder_from_spec().name, encoder_from_spec().dim)
        oracles = _oracles()
        expected = dict(baseline)
        report = {}
        for i, name in enumerate(["frames", "regions", "observations", "map", "diagnostics", "query"]):
            foreign = [t for other, ts in templates.items() if other != name for t in ts]
            mutator = Mutator(templates[name], foreign, seed=SEED + i)
            chosen, skipped = bad_messages(mutator, oracles[name], PER_SOCKET)
            start = time.monotonic()
            if name in proxies:
                for frames in chosen:
                    proxies[name].inject(frames)
                proxies[name].wait_sent(600)
            elif name == "diagnostics":
                for frames in chosen:
                    send_blocking(diag, frames)
            else:
                _query_flood(dealer, chosen)
            report[name] = (len(chosen), skipped, time.monotonic() - start)
            if name == "query":  # requests refused for their content are answered, not "bad messages"
                counted = sum(_query_wire_or_type(f) for f in chosen)
                expected["query_server"] += counted
            else:
                for node in downstream[name]:
                    expected[node] += len(chosen)
        counts = _settled(client, expected, 300)
        print(f"\nfuzz seed {SEED}, {PER_SOCKET} per socket:")
        for name, (sent, skipped, seconds) in report.items():
            print(f"  {name:13s} sent {sent:6d}  (valid mutants not sent: {skipped:5d})  {seconds:6.1f} s")
        print(f"  bad_messages counted: {counts}")
        assert counts == expected
        assert {node: pid_of(supervisor, node) for node in NODES} == pids, "a node died and was restarted"

        # the normal flight, through the same proxies
        for proxy in proxies.values():
            proxy.hold = False
        wait_for(lambda: running.code is not None, 900, "the launch to end after the final map")
    finally:
        client.close()
        supervisor.request_stop()
        running.thread.join(30)
        for proxy in proxies.values():
            proxy.close()
        diag.close()
        dealer.close()
    assert running.code == 0
    assert "restarting" not in (run_dir / "logs" / "launch.log").read_text()
    names = ObservationStore(run_dir / "store", 1).names()
    assert sorted(names) == sorted(set(names)) and len(names) == summary["views"]
    record = latest_map(run_dir / "map")
    assert record["final"] and record["views"] == summary["views"]
    streamed = LanguageMap.load(record["path"])
    np.testing.assert_array_equal(streamed.observed, offline_map.observed)
    np.testing.assert_allclose(streamed.features, offline_map.features, atol=2e-3, rtol=0)


def send_blocking(sock: zmq.Socket, frames: list[bytes], timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            sock.send_multipart(frames, flags=zmq.NOBLOCK)
            return
        except zmq.Again:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.001)


def _query_wire_or_type(frames: list[bytes]) -> bool:
    """A bad request the server counts in bad_messages: it does not decode, or is not a request."""
    try:
        _, message = decode(frames, max_bytes=REQUEST_MAX_BYTES)
    except Exception:
        return True
    return not isinstance(message, (QueryRequest, StatusRequest))


def _query_flood(dealer: zmq.Socket, requests: list[list[bytes]], window: int = 50) -> None:
    """Every request with at most ``window`` unanswered (under the server's reply high-water mark,
    100: beyond it a ROUTER drops replies); each must be answered bad_request."""
    replies, sent = 0, 0
    while replies < len(requests):
        while sent < len(requests) and sent - replies < window:
            dealer.send_multipart([b"", *requests[sent]])
            sent += 1
        if not dealer.poll(30_000):
            raise AssertionError(f"{replies} of {len(requests)} bad requests answered")
        frames = dealer.recv_multipart()
        _, reply = decode(frames[1:])
        assert isinstance(reply, QueryReply) and reply.status == "bad_request", (reply.status, reply.message)
        replies += 1
