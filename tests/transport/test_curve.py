"""CURVE on the query link: an allowed client gets answers, an unknown key or a plain client gets
nothing (NoReply) while the server keeps serving the allowed one; key files and their errors."""

from __future__ import annotations

import stat

import pytest
import zmq

from olsplat_msgs import QueryRequest, StatusRequest
from olsplat_nodes.transport import NoReply, QueryClient, QueryServer, curve
from tests.helpers import wait_for

from .conftest import LOCAL, ServerThread

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def keys(tmp_path):
    """server, alice (allowed) and mallory (not allowed) key pairs; alice's public key in allow/."""
    paths = {name: curve.generate(tmp_path / "keys", name) for name in ("server", "alice", "mallory")}
    allow = tmp_path / "allow"
    allow.mkdir()
    (allow / "alice.key").write_bytes(paths["alice"][0].read_bytes())
    return paths, allow


def test_generate_writes_a_key_pair(tmp_path):
    public, secret = curve.generate(tmp_path / "k", "ground")
    assert public.name == "ground.key" and secret.name == "ground.key_secret"
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    pub, sec = zmq.auth.load_certificate(secret)
    assert pub == zmq.auth.load_certificate(public)[0] and sec and len(pub) == 40
    with pytest.raises(FileExistsError, match=r"ground\.key"):
        curve.generate(tmp_path / "k", "ground")
    assert curve.generate(tmp_path / "k", "ground", overwrite=True)[0] == public
    assert zmq.auth.load_certificate(public)[0] != pub  # a new pair
    for bad in ("", "../up", "a/b", ".hidden"):
        with pytest.raises(ValueError, match="key name"):
            curve.generate(tmp_path / "k", bad)


def test_key_file_errors(keys, tmp_path):
    paths, allow = keys
    with pytest.raises(ValueError, match="no secret key"):
        curve.ServerKeys(paths["server"][0], allow)  # the public file instead of the secret one
    with pytest.raises(FileNotFoundError, match="allow-list directory"):
        curve.ServerKeys(paths["server"][1], tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="secret key file"):
        curve.ClientKeys(tmp_path / "missing.key_secret", paths["server"][0])
    with pytest.raises(FileNotFoundError, match="server public key"):
        curve.ClientKeys(paths["alice"][1], tmp_path / "missing.key")
    assert curve.ServerKeys(paths["server"][1], allow).allowed == ["alice.key"]


def test_allowed_client_is_answered_unknown_and_plain_clients_are_not(ctx, keys):
    paths, allow = keys
    server_keys = curve.ServerKeys(paths["server"][1], allow)
    alice = curve.ClientKeys(paths["alice"][1], paths["server"][0])
    mallory = curve.ClientKeys(paths["mallory"][1], paths["server"][0])
    server = ServerThread(ctx, keys=server_keys)
    with server as endpoint:
        with QueryClient(ctx, endpoint, timeout_s=3.0, keys=alice) as client:
            assert client.request(QueryRequest(request_id="a1", text="road")).request_id == "a1"
        with QueryClient(ctx, endpoint, timeout_s=0.4, keys=mallory) as intruder:
            with pytest.raises(NoReply):
                intruder.request(QueryRequest(request_id="m1", text="road"))
        with QueryClient(ctx, endpoint, timeout_s=0.4) as plain:  # no CURVE at all
            with pytest.raises(NoReply):
                plain.request(StatusRequest(request_id="p1"))
        with QueryClient(ctx, endpoint, timeout_s=3.0, keys=alice) as client:  # still serving alice
            assert client.request(QueryRequest(request_id="a2", text="tree")).request_id == "a2"
        wait_for(lambda: server.stats.get("auth_failures", 0) >= 1)
    assert server.stats["requests"] == 2 and server.stats["bad_requests"] == 0
    assert server.stats["auth_failures"] >= 1


def test_wrong_server_key_gets_no_reply(ctx, keys):
    paths, allow = keys
    # alice is allowed, but she pins mallory's public key as the server's: the handshake fails
    confused = curve.ClientKeys(paths["alice"][1], paths["mallory"][0])
    with ServerThread(ctx, keys=curve.ServerKeys(paths["server"][1], allow)) as endpoint:
        with QueryClient(ctx, endpoint, timeout_s=0.4, keys=confused) as client:
            with pytest.raises(NoReply):
                client.request(StatusRequest(request_id="x"))


def test_two_curve_servers_share_one_authenticator_per_context(ctx, keys, tmp_path):
    paths, allow = keys
    other_allow = tmp_path / "allow2"
    other_allow.mkdir()
    (other_allow / "mallory.key").write_bytes(paths["mallory"][0].read_bytes())
    with (
        ServerThread(ctx, keys=curve.ServerKeys(paths["server"][1], allow)) as first,
        ServerThread(ctx, keys=curve.ServerKeys(paths["server"][1], other_allow)) as second,
    ):
        alice = curve.ClientKeys(paths["alice"][1], paths["server"][0])
        mallory = curve.ClientKeys(paths["mallory"][1], paths["server"][0])
        with QueryClient(ctx, first, timeout_s=3.0, keys=alice) as c:
            assert c.request(StatusRequest(request_id="1")).request_id == "1"
        with QueryClient(ctx, second, timeout_s=3.0, keys=mallory) as c:  # each server its own allow-list
            assert c.request(StatusRequest(request_id="2")).request_id == "2"
        with QueryClient(ctx, second, timeout_s=0.4, keys=alice) as c:
            with pytest.raises(NoReply):
                c.request(StatusRequest(request_id="3"))
    assert curve._AUTHENTICATORS._by_context == {}  # the last server stopped the authenticator


def test_server_start_failure_releases_the_authenticator(ctx, keys):
    paths, allow = keys
    with QueryServer(ctx, LOCAL) as taken:
        with pytest.raises(zmq.ZMQError):
            QueryServer(ctx, taken.endpoint, keys=curve.ServerKeys(paths["server"][1], allow))
    assert curve._AUTHENTICATORS._by_context == {}
