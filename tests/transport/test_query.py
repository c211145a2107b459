"""The query link over real sockets: round trip, timeouts, lazy-pirate recovery, bad requests
answered with bad_request, REQ-client compatibility and a client that ignores garbage replies."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
import zmq

from olsplat_msgs import VERSION, EndOfStream, QueryReply, QueryRequest, StatusReply, StatusRequest, decode, encode
from olsplat_nodes.transport import NoReply, QueryClient, QueryServer
from tests.helpers import free_port, wait_for

from .conftest import LOCAL, ServerThread

pytestmark = pytest.mark.timeout(30)


def test_query_round_trip(ctx):
    with ServerThread(ctx) as endpoint, QueryClient(ctx, endpoint, timeout_s=3.0) as client:
        reply = client.request(QueryRequest(request_id="q1", text="red roof buildings", view="v000"))
        assert isinstance(reply, QueryReply) and reply.request_id == "q1" and reply.text == "red roof buildings"
        status = client.request(StatusRequest())  # no id given: the client makes one up
        assert isinstance(status, StatusReply) and len(status.request_id) == 32
        assert client.stats["replies"] == 2


def test_ipc_endpoint_and_a_reply_with_arrays(ctx, tmp_path):
    def answer(request):
        return QueryReply(
            request_id=request.request_id,
            heatmap=np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4),
            mask=np.eye(3, 4, dtype=np.uint8),
        )

    with (
        ServerThread(ctx, f"ipc://{tmp_path}/q/query.sock", answer=answer) as endpoint,
        QueryClient(ctx, endpoint, timeout_s=3.0) as client,
    ):
        reply = client.request(QueryRequest(request_id="a", text="road", view="v000"))
        assert (
            reply.heatmap.shape == (3, 4)
            and reply.heatmap[2, 3] == 1.0
            and reply.mask.sum() == 3
            and reply.image is None
        )


def test_timeout_raises_no_reply_within_bounded_time(ctx):
    endpoint = f"tcp://127.0.0.1:{free_port()}"  # nobody listening there
    with QueryClient(ctx, endpoint, timeout_s=0.3) as client:
        start = time.monotonic()
        with pytest.raises(NoReply) as info:
            client.request(QueryRequest(request_id="x", text="road"))
        elapsed = time.monotonic() - start
        assert 0.25 <= elapsed < 1.5
        assert info.value.endpoint == endpoint and info.value.timeout == 0.3
        assert str(info.value) == f"no reply from {endpoint} within 0.3 s"
        assert isinstance(info.value, TimeoutError) and client.stats["resets"] == 1
        # lazy pirate: once a server is there, the same client object works
        with ServerThread(ctx, endpoint):
            assert client.request(QueryRequest(request_id="y", text="road")).request_id == "y"


def test_retries_resend_on_a_fresh_socket(ctx):
    with QueryClient(ctx, "tcp://127.0.0.1:1", timeout_s=0.1, retries=2) as client:
        start = time.monotonic()
        with pytest.raises(NoReply):
            client.request(StatusRequest(request_id="s"))
        assert time.monotonic() - start < 1.5
        assert client.stats["timeouts"] == 3 and client.stats["resets"] == 3


def test_a_late_reply_is_never_taken_for_the_next_one(ctx):
    calls = []

    def answer(request):
        calls.append(request.request_id)
        return QueryReply(request_id=request.request_id, text=request.text)

    server = ServerThread(ctx, answer=answer, delay_s=0.4)  # slower than the client's patience
    with server as endpoint, QueryClient(ctx, endpoint, timeout_s=0.2) as client:
        with pytest.raises(NoReply):
            client.request(QueryRequest(request_id="slow", text="first"))
        client.timeout_s = 3.0
        reply = client.request(QueryRequest(request_id="next", text="second"))
        assert reply.request_id == "next" and reply.text == "second"
    assert calls == ["slow", "next"]


def _dealer(ctx, endpoint) -> zmq.Socket:
    sock = ctx.socket(zmq.DEALER)
    sock.linger = 0
    sock.connect(endpoint)
    return sock


def _ask_raw(sock: zmq.Socket, frames: list[bytes]) -> QueryReply:
    sock.send_multipart(frames)
    assert sock.poll(3000), "no answer"
    reply = sock.recv_multipart()
    assert reply[0] == b""  # the server answers in the REQ envelope
    topic, msg = decode(reply[1:])
    assert topic == "query"
    return msg


def test_server_answers_bad_request_to_bad_input_and_keeps_serving(ctx):
    good = encode(QueryRequest(request_id="ok1", text="road"), "query")
    wrong_version = [good[0], msgpack.packb({**msgpack.unpackb(good[1]), "version": 7}), *good[2:]]
    server = ServerThread(ctx, max_bytes=4096)
    with server as endpoint:
        sock = _dealer(ctx, endpoint)
        cases = [
            ([b"", b"query", b"\xc1 garbage"], "", "MalformedMessage"),
            ([b"", *good[:1]], "", "at least 2 frames"),
            ([b"", *wrong_version], "ok1", "UnsupportedVersion"),  # id salvaged from the readable header
            (
                [b"", *encode(EndOfStream(), "query")],
                "",
                "expected QueryRequest or StatusRequest or SplatsRequest or ViewsRequest, got EndOfStream",
            ),
            ([b"", b"query", b"\x00" * 3000, b"\x00" * 3000], "", "MessageTooLarge"),
            ([*good], "", "empty delimiter"),  # a DEALER that forgot the delimiter
        ]
        for frames, request_id, words in cases:
            reply = _ask_raw(sock, frames)
            assert reply.status == "bad_request" and reply.request_id == request_id
            assert words in reply.message, reply.message
        assert _ask_raw(sock, [b"", *good]).status == "ok"
        sock.close(linger=0)
        with QueryClient(ctx, endpoint, timeout_s=3.0) as client:
            assert client.request(QueryRequest(request_id="after", text="road")).request_id == "after"
    assert server.stats["bad_requests"] == len(cases)
    assert server.stats["requests"] == 2


def test_oversized_frame_drops_only_that_client(ctx):
    with ServerThread(ctx, max_bytes=64 * 1024) as endpoint:
        rogue = _dealer(ctx, endpoint)
        rogue.send_multipart([b"", b"query", b"\x00" * (1 << 20)])  # libzmq refuses the frame
        with QueryClient(ctx, endpoint, timeout_s=3.0) as client:
            assert client.request(StatusRequest(request_id="s")).request_id == "s"
        assert not rogue.poll(100)
        rogue.close(linger=0)


def test_req_client_works_without_adding_the_delimiter(ctx):
    with ServerThread(ctx) as endpoint:
        req = ctx.socket(zmq.REQ)
        req.linger = 0
        req.connect(endpoint)
        req.send_multipart(encode(QueryRequest(request_id="req1", text="tree"), "query"))
        assert req.poll(3000)
        topic, reply = decode(req.recv_multipart())
        assert topic == "query" and reply.request_id == "req1" and reply.text == "tree"
        req.close(linger=0)


def test_client_skips_garbage_and_stale_replies(ctx):
    """A fake ROUTER server that first answers garbage, a truncated and a wrong-version reply,
    and a reply to another request, before the real one."""
    router = ctx.socket(zmq.ROUTER)
    router.linger = 0
    router.bind(LOCAL)
    endpoint = router.last_endpoint.decode()
    done = threading.Event()

    def fake_server():
        assert router.poll(3000)
        identity, _delimiter, *body = router.recv_multipart()
        _, request = decode(body)
        good = encode(QueryReply(request_id=request.request_id, text="yes"), "query")
        router.send_multipart([identity, b"", b"query", b"\xc1"])
        router.send_multipart([identity, b"no delimiter"])
        router.send_multipart([identity, b"", *good[:1]])  # truncated
        router.send_multipart(
            [identity, b"", good[0], msgpack.packb({**msgpack.unpackb(good[1]), "version": VERSION + 1}), *good[2:]]
        )
        router.send_multipart([identity, b"", *encode(QueryReply(request_id="old"), "query")])
        router.send_multipart([identity, b"", *good])
        done.set()

    thread = threading.Thread(target=fake_server, daemon=True)
    thread.start()
    with QueryClient(ctx, endpoint, timeout_s=3.0) as client:
        reply = client.request(QueryRequest(request_id="mine", text="q"))
        assert reply.text == "yes"
        assert client.stats["bad_replies"] == 4 and client.stats["stale_replies"] == 1
    thread.join(3)
    assert done.is_set()
    router.close(linger=0)


def test_poll_returns_none_on_timeout(ctx):
    with QueryServer(ctx, LOCAL) as server:
        start = time.monotonic()
        assert server.poll(50) is None
        assert time.monotonic() - start < 1.0
        assert server.endpoint.startswith("tcp://127.0.0.1:") and not server.endpoint.endswith("*")


def test_bound_endpoint_in_use_names_the_endpoint(ctx):
    with QueryServer(ctx, LOCAL) as server:
        with pytest.raises(zmq.ZMQError) as info:
            QueryServer(ctx, server.endpoint)
        assert server.endpoint in "".join(getattr(info.value, "__notes__", []))


def test_server_stats_count_requests(ctx):
    server = ServerThread(ctx)
    with server as endpoint, QueryClient(ctx, endpoint, timeout_s=3.0) as client:
        for i in range(3):
            client.request(StatusRequest(request_id=str(i)))
        wait_for(lambda: server.stats.get("replies") == 3)
    assert server.stats["requests"] == 3 and server.stats["replies"] == 3
