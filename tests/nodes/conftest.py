"""Shared by the node reliability tests: real nodes run in threads (``node.run(stop)``) on real
ZeroMQ sockets (ipc:// in a short temp dir, tcp:// on 127.0.0.1), test-owned raw sockets in
front of and behind them, and heartbeats read from a SUB the test binds where the node's
``diagnostics`` PUB connects. Every wait is a polling loop with a deadline; no sleeps as
synchronisation. Every socket a test opens is closed (the context is destroyed at the end)."""

from __future__ import annotations

import os
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq

from olsplat_msgs import DEFAULT_MAX_BYTES, VERSION, DiagnosticStatus, ImageFrame, WireError, decode, encode
from olsplat_nodes.launcher import Supervisor
from tests.helpers import free_port, wait_for

ENCODE_VIEW = "frame_0003.jpg"  # the tiny scene's view the tests encode and aggregate


# ---------------------------------------------------------------------------------------------
# fixtures


@pytest.fixture
def ctx():
    """A fresh context per test; nodes run on it too (destroy closes whatever is left)."""
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


@pytest.fixture
def sockdir():
    """A short directory for ipc:// socket files (their paths are limited to ~100 characters)."""
    path = Path(tempfile.mkdtemp(prefix="olsn", dir="/tmp"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


def read_rgb(path: Path) -> np.ndarray:
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, path
    return np.ascontiguousarray(bgr[..., ::-1])


def image_frame(camera, image: np.ndarray, seq: int = 1, name: str | None = None) -> ImageFrame:
    return ImageFrame(
        stamp_ns=time.time_ns(),
        seq=seq,
        frame_id="camera",
        name=name or camera.name,
        image=image,
        K=camera.K,
        D=np.asarray(camera.dist, np.float64),
        distortion_model="plumb_bob" if len(camera.dist) else "none",
        world_from_camera=camera.world_from_camera,
        width=camera.width,
        height=camera.height,
    )


@pytest.fixture(scope="session")
def tiny_camera(tiny):
    """(camera, RGB image) of ENCODE_VIEW in the tiny scene."""
    from olsplat_nodes.scene import read_colmap

    scene, _ = tiny
    camera = next(c for c in read_colmap(scene / "sparse" / "0") if c.name == ENCODE_VIEW)
    return camera, read_rgb(scene / "images" / ENCODE_VIEW)


@pytest.fixture(scope="session")
def region_features(tiny_camera):
    """A real RegionFeatures of ENCODE_VIEW: region_encoder.encode_frame with the node's default encoder."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.nodes.region_encoder import encode_frame
    from olsplat_nodes.regions import RegionConfig

    camera, image = tiny_camera
    return encode_frame(image_frame(camera, image), encoder_from_spec(), RegionConfig())


@pytest.fixture(scope="session")
def tiny_run(tiny, region_features, tmp_path_factory):
    """A run directory as the graph leaves it after one view: ``store/`` (the view's observations
    and the manifest), ``views/`` (its photo and camera) and ``map/`` (snapshot version 1 and
    latest.json), made with the same functions the accumulator and refiner nodes call."""
    from olsplat_nodes.method import StoreManifest, add_view, named_method, write_manifest
    from olsplat_nodes.scene import read_ply
    from olsplat_nodes.storage import LanguageMap, ObservationStore, save_view, write_snapshot
    from olsplat_nodes.transport.convert import camera_of, split_bank

    scene, _ = tiny
    run = tmp_path_factory.mktemp("tiny_run")
    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    chosen = named_method("outlangsplat")
    store = ObservationStore(run / "store", len(gaussians), writer=True)
    write_manifest(run / "store", StoreManifest(chosen, region_features.encoder))
    camera = camera_of(region_features)
    label_maps, bank = split_bank(region_features)
    save_view(run / "views", len(store), camera, np.array(region_features.image))
    add_view(gaussians, camera, label_maps, bank, chosen, store)
    features, observed = store.refine(None, chosen.aggregation, only_touched=False)
    language_map = LanguageMap.from_features(features, observed, region_features.encoder)
    write_snapshot(
        run / "map",
        1,
        language_map,
        {
            "views": 1,
            "observed_gaussians": int(observed.sum()),
            "encoder": language_map.encoder,
            "final": True,
        },
        None,
    )
    return run


# ---------------------------------------------------------------------------------------------
# nodes in threads


class NodeThread:
    """``node.run(stop)`` in a thread, as a composed launch runs it. On exit: stop, join, and
    re-raise an exception the node died of."""

    def __init__(self, node):
        self.node = node
        self.stop = threading.Event()
        self.code: int | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name=f"node-{node.name}", daemon=True)

    def _run(self):
        try:
            self.code = self.node.run(self.stop)
        except BaseException as exc:  # reported by the test thread
            self.error = exc

    @property
    def running(self) -> bool:
        return self.thread.is_alive()

    def assert_running(self):
        if self.error is not None:
            raise AssertionError(f"node {self.node.name} died") from self.error
        assert self.running, f"node {self.node.name} exited with code {self.code}"

    def join(self, timeout_s: float) -> int | None:
        self.thread.join(timeout_s)
        if self.error is not None:
            raise AssertionError(f"node {self.node.name} died") from self.error
        return self.code

    def __enter__(self) -> NodeThread:
        self.thread.start()
        return self

    def __exit__(self, exc_type, *_):
        self.stop.set()
        self.thread.join(20)
        assert not self.thread.is_alive(), f"node {self.node.name} did not stop within 20 s"
        if self.error is not None and exc_type is None:
            raise AssertionError(f"node {self.node.name} died") from self.error


# ---------------------------------------------------------------------------------------------
# test-owned sockets


def query_server(scene: Path, sockdir: Path, map_dir: Path, views: Path, **params: Any):
    """A query server over ``scene``'s map with its sockets under ``sockdir`` (query.sock,
    diagnostics.sock, map.sock); ``params`` override any other parameter."""
    from olsplat_nodes.nodes.query_server import QueryServerNode

    return QueryServerNode(
        "query_server",
        {
            "map": str(scene / "map" / "point_cloud.ply"),
            "map_dir": str(map_dir),
            "views": str(views),
            "query_endpoint": f"ipc://{sockdir}/query.sock",
            "diagnostics_bind": f"ipc://{sockdir}/diagnostics.sock",
            "map_in": f"ipc://{sockdir}/map.sock",
            **params,
        },
    )


def raw_socket(ctx, kind: int, endpoint: str, bind: bool, hwm: int = 1000) -> zmq.Socket:
    sock = ctx.socket(kind)
    sock.linger = 0
    sock.sndhwm = sock.rcvhwm = hwm
    if bind:
        sock.bind(endpoint)
    else:
        sock.connect(endpoint)
    return sock


class Tap:
    """A raw SUB socket (bound or connected) that decodes what arrives into ``messages``;
    anything undecodable would be a bug in the node, so it is kept in ``undecodable``."""

    def __init__(self, ctx, endpoint: str, topics: list[str], bind: bool = False):
        self.socket = raw_socket(ctx, zmq.SUB, endpoint, bind)
        for topic in topics:
            self.socket.setsockopt(zmq.SUBSCRIBE, topic.encode())
        self.endpoint = self.socket.last_endpoint.decode() if bind else endpoint
        self.messages: list[tuple[str, Any]] = []
        self.undecodable: list[str] = []

    def poll(self, timeout_ms: int = 0) -> list[tuple[str, Any]]:
        """Take in everything queued (waiting up to ``timeout_ms`` for the first); returns the new ones."""
        new = []
        while self.socket.poll(timeout_ms if not new else 0, zmq.POLLIN):
            frames = self.socket.recv_multipart()
            try:
                new.append(decode(frames))
            except WireError as exc:
                self.undecodable.append(str(exc))
        self.messages.extend(new)
        return new

    def of_type(self, cls) -> list:
        return [m for _, m in self.messages if isinstance(m, cls)]

    def got(self, cls, timeout_ms: int = 50) -> list:
        """``poll`` then every message of type ``cls`` received so far."""
        self.poll(timeout_ms)
        return self.of_type(cls)

    def close(self):
        self.socket.close(linger=0)


class Heartbeats(Tap):
    """The test's diagnostics collector: a SUB bound where the node's heartbeat PUB connects."""

    def __init__(self, ctx, endpoint: str = "tcp://127.0.0.1:*"):
        super().__init__(ctx, endpoint, ["diagnostics"], bind=True)

    def latest(self, node: str) -> dict:
        """The values of the newest heartbeat of ``node`` ({} before the first)."""
        self.poll(0)
        beats = [m for m in self.of_type(DiagnosticStatus) if m.node == node]
        return dict(beats[-1].values) if beats else {}

    def wait(
        self,
        node: str,
        condition: Callable[[dict], bool],
        timeout_s: float,
        what: str,
        step: Callable[[], Any] | None = None,
    ) -> dict:
        """Wait for a heartbeat of ``node`` whose values satisfy ``condition`` (calling ``step``,
        if given, on the way); returns those values."""
        deadline = time.monotonic() + timeout_s
        while True:
            if step is not None:
                step()
            self.poll(50)
            beats = [m.values for m in self.of_type(DiagnosticStatus) if m.node == node]
            found = next((dict(v) for v in reversed(beats) if condition(v)), None)
            if found is not None:
                return found
            if time.monotonic() > deadline:
                pytest.fail(
                    f"timed out after {timeout_s} s waiting for a heartbeat of {node} with {what}; "
                    f"last values: {beats[-1:]}"
                )


# ---------------------------------------------------------------------------------------------
# bad messages


def _repack(header: bytes, **change) -> bytes:
    doc = msgpack.unpackb(header, raw=False)
    doc.update(change)
    return msgpack.packb(doc, use_bin_type=True)


def bad_variants(good: list[bytes]) -> dict[str, list[bytes]]:
    """Corruptions of one valid encoded message (``encode(msg, topic)``), keeping the topic frame
    (a SUB filters on it, so garbage must carry the topic to reach the node at all): every one is
    checked here to be refused by ``decode``."""
    topic, header, *arrays = good
    rng = np.random.default_rng(7)
    flipped = bytearray(header)
    for i in (0, len(header) // 3, len(header) // 2):
        flipped[i] ^= 0xFF
    variants = {
        "garbage": [topic, rng.integers(0, 256, 300, dtype=np.uint8).tobytes()],
        "not msgpack": [topic, b"\xc1\xc1\xc1", *arrays],
        "truncated header": [topic, header[: len(header) // 2], *arrays],
        "flipped header bytes": [topic, bytes(flipped), *arrays],
        "wrong version": [topic, _repack(header, version=VERSION + 1), *arrays],
        "unknown schema": [topic, _repack(header, schema="olsplat_msgs/NoSuchMessage"), *arrays],
        "single frame": [topic],
        "extra frame": [topic, header, *arrays, b"surplus"],
        "empty header": [topic, b"", *arrays],
    }
    if arrays:
        variants["dropped array frame"] = [topic, header, *arrays[:-1]]
        variants["truncated array frame"] = [topic, header, *arrays[:-1], arrays[-1][:-1] if arrays[-1] else b"x"]
    for name, frames in variants.items():
        try:
            decode(frames)
        except WireError:
            continue
        raise AssertionError(f"bad variant {name!r} decodes: the test's corruption is not a corruption")
    return variants


def oversized(topic: str, limit: int = DEFAULT_MAX_BYTES) -> list:
    """One frame of ``limit`` + 1 bytes (give the receiving socket's limit): libzmq refuses it
    from its size header (ZMQ_MAXMSGSIZE) and drops that connection; only a little of it is read."""
    return [topic.encode(), b"\x80", zmq.Frame(bytes(limit + 1))]


def accumulator_params(scene: Path, folder: Path, sockdir: Path, beats: Heartbeats, **extra) -> dict:
    """An accumulator over the scene's map with its store and views in ``folder``, its sockets in
    ``sockdir`` (regions.sock in, observations.sock out) and its heartbeats to ``beats``."""
    return {
        "map": str(scene / "map" / "point_cloud.ply"),
        "store": str(folder / "store"),
        "views": str(folder / "views"),
        "regions_in": f"ipc://{sockdir}/regions.sock",
        "observations_out": f"ipc://{sockdir}/observations.sock",
        "diagnostics": beats.endpoint,
        **extra,
    }


def send(sock: zmq.Socket, frames: list) -> None:
    sock.send_multipart(frames, copy=False)


def send_msg(sock: zmq.Socket, msg, topic: str) -> None:
    sock.send_multipart(encode(msg, topic))


# ---------------------------------------------------------------------------------------------
# the whole graph on the tiny preset (launch/replay.yaml), as the graph-level tests run it

REPO = Path(__file__).resolve().parents[2]


def launch_tiny(scene: Path, run_dir: Path, port: int, *extra: str):
    """The replay launch over ``scene`` into ``run_dir``, query server on 127.0.0.1:``port``;
    ``extra`` overrides as on the command line."""
    from olsplat_nodes.launcher import load_launch

    ply = scene / "map" / "point_cloud.ply"
    overrides = [
        f"ingest.source={scene / 'replay.mcap'}",
        f"query_server.map={ply}",
        f"accumulator.map={ply}",
        f"refiner.map={ply}",
        f"query_server.query_endpoint=tcp://127.0.0.1:{port}",
        "refiner.period_s=2",
        "ingest.ack_timeout_s=10",
        *extra,
    ]
    return load_launch(REPO / "launch" / "replay.yaml", overrides=overrides, run_dir=str(run_dir))


def fly_and_kill(scene: Path, run_dir: Path, victim: str, *extra: str, stored: int = 2, kills: int = 1) -> int:
    """Launch the tiny flight into ``run_dir``, kill -9 ``victim`` once ``stored`` views are in
    the store (``kills`` times in a row, each time once it is back), and return the launch's
    exit code after it has ended by itself with the final map."""
    supervisor = Supervisor(launch_tiny(scene, run_dir, free_port(), *extra))
    running = Background(supervisor)
    try:
        store = run_dir / "store" / "views"
        wait_for(lambda: store.is_dir() and len(list(store.iterdir())) >= stored, 300, f"{stored} stored views")
        for _ in range(kills):
            pid = pid_of(supervisor, victim)
            assert pid, f"the supervisor reports the {victim}'s pid"
            os.kill(pid, signal.SIGKILL)
            wait_for(lambda old=pid: pid_of(supervisor, victim) not in (None, old), 60, f"the {victim} restarted")
        wait_for(lambda: running.code is not None, 480, "the launch to end after the final map")
    finally:
        supervisor.request_stop()
        running.thread.join(30)
    return running.code


class Background:
    """``supervisor.run()`` in a thread; ``code`` is its exit code once it has ended."""

    def __init__(self, supervisor):
        self.supervisor, self.code = supervisor, None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        self.code = self.supervisor.run()


def pid_of(supervisor, node: str) -> int | None:
    return supervisor.pids.get(node) if isinstance(supervisor.pids, dict) else None


@pytest.fixture(scope="session")
def offline_map(tiny_map):
    """The tiny flight aggregated offline (``olsplat aggregate``): what an uninterrupted run gives."""
    from olsplat_nodes.storage import LanguageMap

    return LanguageMap.load(tiny_map)


def refiner(scene: Path, sockdir: Path, store: Path, map_dir: Path, diagnostics: str):
    """A refiner over ``store`` whose passes come only from EndOfStream (no periodic pass),
    reading observations.sock and writing map.sock under ``sockdir``."""
    from olsplat_nodes.nodes.refiner import RefinerNode

    return RefinerNode(
        "refiner",
        {
            "map": str(scene / "map" / "point_cloud.ply"),
            "store": str(store),
            "map_dir": str(map_dir),
            "period_s": 3600.0,  # no periodic pass: only EndOfStream makes a map here
            "observations_in": f"ipc://{sockdir}/observations.sock",
            "map_out": f"ipc://{sockdir}/map.sock",
            "diagnostics": diagnostics,
        },
    )
