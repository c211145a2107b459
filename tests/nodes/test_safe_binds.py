"""The ground link is not opened by accident: a query server on an address other computers can
reach refuses to start without CURVE unless ``insecure: true`` says so (and then every status
it gives says INSECURE); a secret key file others can read is refused."""

from __future__ import annotations

import json
import os

import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.nodes.query_server import QueryServerNode, is_public
from olsplat_nodes.params import ParameterError
from olsplat_nodes.transport import curve
from tests.helpers import free_port, wait_for

from .conftest import NodeThread

pytestmark = pytest.mark.timeout(120)


def _params(tiny, tmp_path, endpoint, **more):
    scene, _ = tiny
    return {
        "map": str(scene / "map" / "point_cloud.ply"),
        "map_dir": str(tmp_path / "map"),
        "views": str(tmp_path / "views"),
        "query_endpoint": endpoint,
        "diagnostics_bind": f"ipc://{tmp_path}/d.sock",
        "map_in": f"ipc://{tmp_path}/m.sock",
        **more,
    }


def test_which_endpoints_are_public():
    for endpoint in ("tcp://0.0.0.0:5600", "tcp://*:5600", "tcp://192.168.1.7:5600", "tcp://eth0:5600", "tcp://[::]:1"):
        assert is_public(endpoint), endpoint
    for endpoint in ("tcp://127.0.0.1:5600", "tcp://127.0.1.1:5600", "tcp://localhost:1", "tcp://[::1]:1", "ipc:///x"):
        assert not is_public(endpoint), endpoint


def test_a_public_bind_without_curve_is_refused_unless_insecure(tiny, tmp_path, capsys):
    port = free_port()
    with pytest.raises(ParameterError, match=r"tcp://0\.0\.0\.0:\d+ can be reached from other computers"):
        QueryServerNode("qs", _params(tiny, tmp_path, f"tcp://0.0.0.0:{port}"))

    node = QueryServerNode("qs", _params(tiny, tmp_path, f"tcp://0.0.0.0:{port}", insecure=True))
    with NodeThread(node) as running:
        connect = f"tcp://127.0.0.1:{port}"

        def status():
            code = main(["ground", "status", "--json", "--connect", connect, "--timeout", "1"])
            out = capsys.readouterr().out
            return json.loads(out) if code == 0 else None

        reply = wait_for(status, 30, "the insecure query server")
        own = reply["nodes"][0]
        assert own["level"] == 1 and own["message"].startswith(f"INSECURE: tcp://0.0.0.0:{port}")
        running.assert_running()


def test_a_secret_key_others_can_read_is_refused(tiny, tmp_path):
    _, secret = curve.generate(tmp_path / "keys", "server")
    (tmp_path / "allow").mkdir()
    params = _params(
        tiny, tmp_path, f"tcp://0.0.0.0:{free_port()}", server_secret=str(secret), allow_dir=str(tmp_path / "allow")
    )
    QueryServerNode("qs", params)  # mode 0600 as `generate` writes it: accepted
    os.chmod(secret, 0o644)
    with pytest.raises(ParameterError, match=r"server_secret: .*readable by others \(mode 644\); .*chmod 600"):
        QueryServerNode("qs", params)
    with pytest.raises(ParameterError, match="server_secret: secret key file not found"):
        QueryServerNode("qs", {**params, "server_secret": str(tmp_path / "missing.key_secret")})
