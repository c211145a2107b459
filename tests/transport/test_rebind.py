"""A node restarted in the launcher's composed mode binds its ``inproc://`` name again at once,
while libzmq's reaper may still hold the closed socket's name: the transport's bind waits for it
(``_sockets.attach``), and still reports a name another open socket holds."""

from __future__ import annotations

import pytest
import zmq

from olsplat_nodes.transport import Publisher, Subscriber
from olsplat_nodes.transport._sockets import attach


def test_a_closed_sockets_inproc_name_can_be_bound_again_at_once():
    ctx = zmq.Context()
    try:
        for _ in range(300):  # raw libzmq refuses about one rebind in ten here ("Address already in use")
            talker = Publisher(ctx, "inproc://restart")
            listener = Subscriber(ctx, "inproc://restart", None)
            talker.close()
            listener.close()
    finally:
        ctx.term()


def test_a_name_another_open_socket_holds_is_still_refused():
    ctx = zmq.Context()
    holder = ctx.socket(zmq.PUB)
    other = ctx.socket(zmq.PUB)
    try:
        holder.bind("inproc://taken")
        with pytest.raises(zmq.ZMQError, match="Address already in use") as caught:
            attach(other, ["inproc://taken"], bind=True, inproc_wait_s=0.2)
        assert "while binding inproc://taken" in caught.value.__notes__
    finally:
        holder.close(linger=0)
        other.close(linger=0)
        ctx.term()
