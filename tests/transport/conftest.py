"""Real ZeroMQ sockets on 127.0.0.1 with ports chosen by the kernel (``tcp://127.0.0.1:*``) or
ipc paths in tmp_path; a fresh context per test; servers in threads; waits are polling loops with
deadlines, never sleeps."""

from __future__ import annotations

import queue
import threading
import time

import pytest
import zmq

from olsplat_msgs import QueryReply, QueryRequest, StatusReply
from olsplat_nodes.transport import QueryServer

LOCAL = "tcp://127.0.0.1:*"


@pytest.fixture
def ctx():
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


def echo_answer(request):
    if isinstance(request, QueryRequest):
        return QueryReply(request_id=request.request_id, text=request.text, view=request.view, map_version=1)
    return StatusReply(request_id=request.request_id, map_version=1)


class ServerThread:
    """A QueryServer living in its own thread (sockets stay in the thread that made them),
    answering with ``answer(request)`` after ``delay_s``."""

    def __init__(self, context, endpoint=LOCAL, keys=None, answer=echo_answer, delay_s=0.0, **kwargs):
        self._args = (context, endpoint, keys, kwargs)
        self.answer, self.delay_s = answer, delay_s
        self.stop = threading.Event()
        self._ready: queue.Queue = queue.Queue()
        self.stats: dict = {}
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        context, endpoint, keys, kwargs = self._args
        try:
            server = QueryServer(context, endpoint, keys=keys, **kwargs)
        except Exception as exc:  # surface start-up errors in the test thread
            self._ready.put(exc)
            return
        self._ready.put(server.endpoint)
        try:
            while not self.stop.is_set():
                got = server.poll(20)
                if got is not None:
                    identity, request = got
                    if self.delay_s:
                        time.sleep(self.delay_s)  # simulates a slow server, not a wait in the test
                    server.reply(identity, self.answer(request))
                self.stats = dict(server.stats)
        finally:
            self.stats = dict(server.stats)
            server.close()

    def __enter__(self) -> str:
        self.thread.start()
        endpoint = self._ready.get(timeout=5)
        if isinstance(endpoint, Exception):
            raise endpoint
        self.endpoint = endpoint
        return endpoint

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(timeout=5)
        assert not self.thread.is_alive()
