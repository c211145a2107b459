"""``olsplat ground query/status`` against a real query server node (in a thread, on real
sockets): JSON output, heatmap and mask PNGs over a view, the exit code and one-line error of a
wrong endpoint, and CURVE on the ground link (an allowed key is answered, any other client gets
nothing, and the allowed one still works afterwards)."""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import sys

import cv2
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.nodes.query_server import QueryServerNode
from olsplat_nodes.transport import curve
from olsplat_nodes.viz import LEGEND_H
from tests.helpers import free_port, wait_for

from .conftest import ENCODE_VIEW, NodeThread

pytestmark = pytest.mark.timeout(120)


@contextlib.contextmanager
def query_server(ctx, sockdir, tiny, map_dir, views, **params):
    """A QueryServerNode in a thread; yields its query endpoint once it answers."""
    scene, _ = tiny
    endpoint = f"ipc://{sockdir}/query.sock"
    node = QueryServerNode(
        "query_server",
        {
            "map": str(scene / "map" / "point_cloud.ply"),
            "map_dir": str(map_dir),
            "views": str(views),
            "query_endpoint": endpoint,
            "diagnostics_bind": f"ipc://{sockdir}/diagnostics.sock",
            "map_in": f"ipc://{sockdir}/map.sock",
            **params,
        },
    )
    with NodeThread(node) as running:
        yield endpoint
        running.assert_running()


def ground(capsys, *argv) -> tuple[int, str, str]:
    """Run ``olsplat ground ARGV`` in this process; returns (exit code, stdout, stderr)."""
    code = main(["ground", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def wait_until_up(capsys, endpoint, *keys):
    """The node thread reads the map PLY before it binds: ask until it answers."""
    wait_for(
        lambda: ground(capsys, "status", "--json", "--connect", endpoint, "--timeout", 1, *keys)[0] == 0,
        20,
        "the query server",
    )


def test_status_and_query_print_json(ctx, sockdir, tiny, tiny_run, capsys):
    with query_server(ctx, sockdir, tiny, tiny_run / "map", tiny_run / "views") as endpoint:
        wait_until_up(capsys, endpoint)
        code, out, err = ground(capsys, "status", "--json", "--connect", endpoint)
        assert code == 0 and err == ""
        status = json.loads(out)
        assert status["map_version"] == 1 and status["nodes"][0]["node"] == "query_server"
        assert status["nodes"][0]["level"] == 0 and "bad_messages" in status["nodes"][0]["values"]

        # the tiny town's one red roof is too small for a 3D instance once a query must beat the
        # aerial vocabulary (query/negatives.py); its parking lots are not
        code, out, err = ground(capsys, "query", "parking lot", "--json", "--connect", endpoint, "--timeout", 30)
        assert code == 0, err
        answer = json.loads(out)
        assert answer["status"] == "ok" and answer["text"] == "parking lot" and answer["map_version"] == 1
        found = [i for i in answer["instances"] if i["kind"] == "3d"]
        assert found and all(len(i["centroid"]) == 3 and i["n_gaussians"] > 0 for i in found)

        code, out, _ = ground(capsys, "status", "--connect", endpoint)  # the human-readable table
        assert code == 0 and out.startswith("map version 1") and "query_server" in out


def test_query_over_a_view_writes_the_preview_then_the_full_pngs(
    ctx, sockdir, tiny, tiny_run, tmp_path, capsys, monkeypatch
):
    from olsplat_nodes.query import service

    monkeypatch.setattr(service, "PREVIEW_MAX_SIDE", 160)  # the tiny views are 320 px wide: previews of half
    out_dir = tmp_path / "pictures"
    with query_server(ctx, sockdir, tiny, tiny_run / "map", tiny_run / "views") as endpoint:
        wait_until_up(capsys, endpoint)
        code, out, err = ground(
            capsys,
            "query",
            "red roof buildings",
            "--view",
            ENCODE_VIEW,
            "--out",
            out_dir,
            "--connect",
            endpoint,
            "--timeout",
            30,
        )
    assert code == 0, err
    stem = f"{ENCODE_VIEW.rsplit('.', 1)[0]}_red_roof_buildings"
    pictures = sorted(out_dir.iterdir())
    kinds = ("heatmap", "mask", "preview_heatmap", "preview_mask")
    assert [p.name for p in pictures] == [f"{stem}_{kind}.png" for kind in kinds]
    for picture in pictures:
        assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        size = (120, 160) if "preview" in picture.name else (240, 320)
        assert cv2.imread(str(picture)).shape == (size[0] + LEGEND_H, size[1], 3)  # the view, then its legend
    assert f"view {ENCODE_VIEW}" in out and "pictures ->" in out
    assert out.index("preview pictures ->") < out.index(f"view {ENCODE_VIEW}")  # the preview came first


def test_query_before_any_map_says_so(ctx, sockdir, tiny, tmp_path, capsys):
    with query_server(ctx, sockdir, tiny, tmp_path / "map", tmp_path / "views") as endpoint:
        wait_until_up(capsys, endpoint)
        code, out, _ = ground(capsys, "query", "road", "--json", "--connect", endpoint, "--timeout", 2)
        assert code == 0 and json.loads(out)["status"] == "no_map"
        code, out, _ = ground(capsys, "query", "road", "--view", ENCODE_VIEW, "--connect", endpoint, "--timeout", 2)
        assert code == 0 and out.startswith('"road": no_map: no map yet')


def _unused_tcp_endpoint() -> str:
    return f"tcp://127.0.0.1:{free_port()}"


@pytest.mark.parametrize("command", [["status"], ["query", "road"]])
def test_a_wrong_endpoint_exits_1_with_one_line_naming_it(command, capsys):
    for endpoint in (
        _unused_tcp_endpoint(),
        "tcp://127.0.0.1",
        "nosuch://x",
    ):  # nobody there; no port; no such transport
        code, out, err = ground(capsys, *command, "--connect", endpoint, "--timeout", 0.3)
        assert code == 1 and out == "", (endpoint, out, err)
        assert err.count("\n") == 1 and endpoint in err and err.startswith(f"olsplat ground {command[0]}: error: "), err


def test_the_installed_command_exits_1_on_a_wrong_endpoint_and_says_what_to_check():
    endpoint = _unused_tcp_endpoint()
    done = subprocess.run(
        [sys.executable, "-m", "olsplat_nodes.cli", "ground", "status", "--connect", endpoint, "--timeout", "0.3"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.startswith(f"olsplat ground status: error: no reply from {endpoint} within 0.3 s: ")
    assert "graph running" in done.stderr and "olsplat launch" in done.stderr and done.stderr.count("\n") == 1


def test_curve_ground_link_answers_only_allowed_keys(ctx, sockdir, tiny, tiny_run, tmp_path, capsys):
    _, server_secret = curve.generate(tmp_path / "server", "query_server")
    server_public = tmp_path / "server" / "query_server.key"
    ground1_public, ground1_secret = curve.generate(tmp_path / "ground1", "ground1")
    _, intruder_secret = curve.generate(tmp_path / "intruder", "intruder")
    (tmp_path / "allow").mkdir()
    shutil.copy(ground1_public, tmp_path / "allow")  # the allow-list holds ground1's public key only

    allowed = ["--client-key", ground1_secret, "--server-key", server_public]
    intruder = ["--client-key", intruder_secret, "--server-key", server_public]
    with query_server(
        ctx,
        sockdir,
        tiny,
        tiny_run / "map",
        tiny_run / "views",
        server_secret=str(server_secret),
        allow_dir=str(tmp_path / "allow"),
    ) as endpoint:
        wait_until_up(capsys, endpoint, *allowed)
        code, out, err = ground(
            capsys, "query", "red roof buildings", "--json", "--connect", endpoint, "--timeout", 30, *allowed
        )
        assert code == 0 and json.loads(out)["status"] == "ok", err

        for keys in (intruder, []):  # a key not on the list, and a client without CURVE: no answer at all
            code, out, err = ground(capsys, "status", "--json", "--connect", endpoint, "--timeout", 1, *keys)
            assert (
                code == 1
                and out == ""
                and err.startswith(f"olsplat ground status: error: no reply from {endpoint} within 1 s: ")
            )

        code, out, err = ground(capsys, "status", "--json", "--connect", endpoint, *allowed)  # still served
        assert code == 0, err
        values = json.loads(out)["nodes"][0]["values"]
        assert values["auth_failures"] >= 1 and values["bad_requests"] == 0
