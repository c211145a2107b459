"""Publisher/Subscriber over real sockets: round trip, gap counting, latest-wins drops, and bad
frames that are counted while the subscriber keeps receiving."""

from __future__ import annotations

import time

import msgpack
import numpy as np
import pytest
import zmq

from olsplat_msgs import EndOfStream, ImageFrame, ObservationsAdded, encode
from olsplat_nodes.transport import Publisher, Subscriber
from tests.helpers import wait_for

from .conftest import LOCAL

pytestmark = pytest.mark.timeout(30)


def _frame(seq: int, frame_id: str = "cam0", size: int = 4) -> ImageFrame:
    image = np.full((size, size + 1, 3), seq % 256, np.uint8)
    return ImageFrame(
        seq=seq,
        stamp_ns=1000 + seq,
        frame_id=frame_id,
        name=f"v{seq:03d}",
        image=image,
        K=np.eye(3),
        D=np.zeros(0),
        world_from_camera=np.eye(4),
        width=size + 1,
        height=size,
    )


def _connected(send: callable, sub: Subscriber, timeout_s: float = 3.0) -> tuple:
    """Repeat ``send()`` until the subscriber gets a message (ZeroMQ's slow joiner: the first
    messages after connecting are lost); returns the message that arrived."""
    got = []
    wait_for(lambda: got, timeout_s, step=lambda: (send(), got.extend(sub.drain(20))))
    assert got, "subscriber never received anything"
    return got[-1]


@pytest.mark.parametrize("transport", ["tcp", "ipc"])
def test_round_trip(ctx, tmp_path, transport):
    endpoint = LOCAL if transport == "tcp" else f"ipc://{tmp_path}/run/frames.sock"
    with Publisher(ctx, endpoint, hwm=16) as pub, Subscriber(ctx, pub.endpoint, "frames", hwm=16) as sub:
        _connected(lambda: pub.send("frames", EndOfStream(frame_id="warmup")), sub)
        pub.send("frames", _frame(5))
        pub.send("frames", EndOfStream(seq=6, frame_id="cam0", source="replay", frames=1, names=["v005"]))
        got = []
        wait_for(lambda: len([m for _, m in got if m.frame_id == "cam0"]) >= 2, step=lambda: got.extend(sub.drain(20)))
        ours = [(t, m) for t, m in got if m.frame_id == "cam0"]
        assert [t for t, _ in ours] == ["frames", "frames"]
        frame, eos = ours[0][1], ours[1][1]
        assert isinstance(frame, ImageFrame) and frame.name == "v005" and frame.image.shape == (4, 5, 3)
        assert np.array_equal(frame.image, _frame(5).image) and not frame.image.flags.writeable
        assert isinstance(eos, EndOfStream) and eos.names == ["v005"]
        assert sub.stats["bad_messages"] == 0 and pub.stats["published"] >= 3


def test_exact_topic_match(ctx):
    with Publisher(ctx, LOCAL, hwm=16) as pub, Subscriber(ctx, pub.endpoint, ["frames"], hwm=16) as sub:
        _connected(lambda: pub.send("frames", EndOfStream(frame_id="warmup")), sub)
        pub.send("frames_debug", EndOfStream(frame_id="x"))  # shares the zmq prefix, not the topic
        pub.send("regions", EndOfStream(frame_id="x"))  # not subscribed at all: filtered by libzmq
        pub.send("frames", EndOfStream(frame_id="y"))
        got = []
        wait_for(lambda: any(m.frame_id == "y" for _, m in got), step=lambda: got.extend(sub.drain(20)))
        assert all(m.frame_id != "x" for _, m in got)
        assert sub.stats["other_topics"] == 1


def test_gaps_counted_per_stream_when_publisher_skips_seq(ctx):
    with Publisher(ctx, LOCAL, hwm=100) as pub, Subscriber(ctx, pub.endpoint, "observations", hwm=100) as sub:
        _connected(lambda: pub.send("observations", ObservationsAdded(frame_id="warmup")), sub)
        for seq in (10, 11, 14, 15, 20):  # missing 12, 13 and 16..19
            pub.send("observations", ObservationsAdded(seq=seq, frame_id="acc"))
        for seq in (3, 4):  # a second stream (other frame_id) keeps its own count
            pub.send("observations", ObservationsAdded(seq=seq, frame_id="acc2"))
        pub.send("observations", ObservationsAdded(seq=20, frame_id="acc"))  # repeated seq
        pub.send("observations", ObservationsAdded(seq=0, frame_id="acc"))  # publisher restarted
        got = []
        wait_for(
            lambda: len([m for _, m in got if m.frame_id.startswith("acc")]) >= 9,
            step=lambda: got.extend(sub.drain(20)),
        )
        assert sub.stats["gaps"] == 6
        assert sub.gaps_by_stream == {("observations", "ObservationsAdded", "acc"): 6}
        assert sub.stats["duplicates"] == 1 and sub.stats["seq_resets"] == 1


def test_slow_consumer_drops_are_counted_as_gaps(ctx):
    """inproc has no kernel buffer, so the high-water marks alone decide: latest wins, and what
    was dropped shows up as gaps once a later message arrives."""
    with Publisher(ctx, "inproc://frames", hwm=2) as pub, Subscriber(ctx, "inproc://frames", "frames", hwm=2) as sub:
        _connected(lambda: pub.send("frames", EndOfStream(frame_id="warmup")), sub)
        sub.drain(0)
        sent = 50
        for seq in range(sent):  # the subscriber reads nothing meanwhile; PUB never blocks
            assert pub.send("frames", _frame(seq))
        received = [m.seq for _, m in sub.drain(0) if m.frame_id == "cam0"]
        assert 0 < len(received) < sent
        # PUB notices that the queue has room again only a little later: send until one gets through
        seq = sent - 1
        while (got := sub.recv(20)) is None and seq < sent + 200:
            seq += 1
            pub.send("frames", _frame(seq))
        assert got is not None
        received.append(got[1].seq)
        assert sub.stats["gaps"] == received[-1] - received[0] + 1 - len(received) > 0
        assert sub.gaps_by_stream[("frames", "ImageFrame", "cam0")] == sub.stats["gaps"]


def _raw_pub(ctx) -> tuple[zmq.Socket, str]:
    sock = ctx.socket(zmq.PUB)
    sock.linger = 0
    sock.bind(LOCAL)
    return sock, sock.last_endpoint.decode()


def test_bad_frames_are_counted_and_the_next_good_message_arrives(ctx, caplog):
    raw, endpoint = _raw_pub(ctx)
    good = encode(_frame(1), "frames")
    wrong_version = [good[0], msgpack.packb({**msgpack.unpackb(good[1]), "version": 99}), *good[2:]]
    with Subscriber(ctx, endpoint, "frames", hwm=100, max_bytes=4096) as sub:
        _connected(lambda: raw.send_multipart(encode(EndOfStream(frame_id="warmup"), "frames")), sub)
        bad_messages = [
            [b"frames", b"\xc1 not msgpack"],  # garbage
            good[:3],  # truncated (frames missing)
            [good[0], good[1][:-5], *good[2:]],  # truncated header
            wrong_version,
            [b"frames", b"\x00" * 3000, b"\x00" * 3000],  # every frame < MAXMSGSIZE, total > max_bytes
        ]
        for frames in bad_messages:
            raw.send_multipart(frames)
        raw.send_multipart(encode(_frame(7), "frames"))
        got = sub.recv(3000)
        while got is not None and got[1].frame_id == "warmup":
            got = sub.recv(3000)
        assert got is not None and got[1].seq == 7
        assert sub.stats["bad_messages"] == 5
        assert dict(sub.bad_by_error) == {"MalformedMessage": 3, "UnsupportedVersion": 1, "MessageTooLarge": 1}
        assert "dropped a message" in caplog.text  # logged (rate-limited: once here)
    raw.close()


def test_an_oversized_frame_is_refused_by_libzmq_and_the_stream_recovers(ctx):
    raw, endpoint = _raw_pub(ctx)
    with Subscriber(ctx, endpoint, "frames", hwm=100, max_bytes=64 * 1024) as sub:
        _connected(lambda: raw.send_multipart(encode(EndOfStream(frame_id="warmup"), "frames")), sub)
        raw.send_multipart([b"frames", b"\x00" * (1 << 20)])  # one 1 MiB frame: the connection is dropped
        # the subscriber reconnects by itself; good messages flow again
        got = _connected(lambda: raw.send_multipart(encode(_frame(9), "frames")), sub, timeout_s=5.0)
        assert got[1].seq == 9
        assert sub.stats["reconnects"] >= 1
    raw.close()


def test_recv_times_out_and_never_raises_on_a_garbage_flood(ctx):
    raw, endpoint = _raw_pub(ctx)
    with Subscriber(ctx, endpoint, None, hwm=1000) as sub:
        _connected(lambda: raw.send_multipart(encode(EndOfStream(frame_id="warmup"), "any")), sub)
        for _ in range(200):
            raw.send_multipart([b"x", b"\xc1"])
        start = time.monotonic()
        assert sub.recv(100) is None
        assert time.monotonic() - start < 1.0
        wait_for(lambda: sub.stats["bad_messages"] == 200, step=lambda: sub.drain(10))
        assert sub.stats["bad_messages"] == 200
    raw.close()
