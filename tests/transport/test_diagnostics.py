"""Heartbeats reach a bound collector; beats are rate-limited; silent nodes turn STALE; and the
``olsplat keys generate`` command."""

from __future__ import annotations

import stat
import time

import pytest
import zmq

from olsplat_msgs import DiagnosticStatus
from olsplat_nodes.cli import main
from olsplat_nodes.transport import Diagnostics, DiagnosticsCollector
from tests.helpers import wait_for

from .conftest import LOCAL

pytestmark = pytest.mark.timeout(30)


def test_beats_arrive_at_a_bound_collector(ctx):
    with (
        DiagnosticsCollector(ctx, LOCAL, stale_after_s=5.0) as collector,
        Diagnostics(ctx, collector.endpoint, "accumulator", period_s=0.02) as diag,
    ):
        values = {"rate_hz": 2.5, "drops": 3, "state": "running"}
        # the first beats are lost while the PUB connects (slow joiner): beat until one arrives
        assert wait_for(lambda: collector.poll(10), step=lambda: diag.beat(DiagnosticStatus.WARN, "slow", values))
        (node,) = collector.nodes()
        assert node["node"] == "accumulator" and node["frame_id"] == "accumulator"
        assert node["level"] == DiagnosticStatus.WARN and node["message"] == "slow" and node["values"] == values
        assert 0 <= node["age_s"] < 5.0 and node["stamp_ns"] > 0
        assert collector.stats["bad_messages"] == 0


def test_beat_is_rate_limited_and_beat_now_is_not(ctx):
    with Diagnostics(ctx, "tcp://127.0.0.1:1", "n", period_s=60.0) as diag:
        assert diag.beat(0, "up") is True
        assert diag.beat(0, "up") is False  # within the period
        assert diag.beat_now(2, "failed") is True
        assert diag.seq == 2


def test_two_nodes_and_stale_detection(ctx):
    with (
        DiagnosticsCollector(ctx, LOCAL, stale_after_s=0.5) as collector,
        Diagnostics(ctx, collector.endpoint, "ingest", period_s=0.01) as a,
        Diagnostics(ctx, collector.endpoint, "refiner", period_s=0.01) as b,
    ):

        def both_seen():
            collector.poll(5)
            return {n["node"] for n in collector.nodes()} == {"ingest", "refiner"}

        assert wait_for(both_seen, step=lambda: (a.beat(0), b.beat(0)))
        # refiner goes silent; ingest keeps beating
        levels = lambda: {n["node"]: n["level"] for n in collector.nodes()}  # noqa: E731
        assert wait_for(
            lambda: levels()["refiner"] == DiagnosticStatus.STALE, step=lambda: (a.beat(0), collector.poll(5))
        )
        assert levels()["ingest"] == DiagnosticStatus.OK


def test_collector_counts_garbage(ctx):
    with DiagnosticsCollector(ctx, LOCAL) as collector:
        raw = ctx.socket(zmq.PUB)
        raw.linger = 0
        raw.connect(collector.endpoint)
        start = time.monotonic()
        wait_for(
            lambda: collector.stats["bad_messages"] > 0,
            step=lambda: (raw.send_multipart([b"diagnostics", b"junk"]), collector.poll(5)),
        )
        assert collector.stats["bad_messages"] > 0 and collector.nodes() == []
        assert time.monotonic() - start < 3.0
        raw.close(linger=0)


def test_collector_survives_an_oversized_frame(ctx):
    """The collector binds; a sender whose frame exceeds max_bytes is cut off by libzmq and, being
    the connecting side, comes back by itself."""
    with (
        DiagnosticsCollector(ctx, LOCAL, max_bytes=64 * 1024) as collector,
        Diagnostics(ctx, collector.endpoint, "query_server", period_s=0.0) as diag,
    ):
        assert wait_for(lambda: collector.poll(10), step=lambda: diag.beat(0))
        message = lambda: (collector.poll(10), collector.nodes()[0]["message"])[1]  # noqa: E731
        diag.beat_now(0, "before")
        assert wait_for(lambda: message() == "before")
        diag.socket.send_multipart([b"diagnostics", b"\x00" * (1 << 20)])  # libzmq cuts this connection
        # every "back" beat is sent after the oversized frame: one arriving proves the link recovered
        assert wait_for(lambda: message() == "back", timeout_s=5.0, step=lambda: diag.beat_now(0, "back"))


def test_keys_generate_command(tmp_path, capsys):
    assert main(["keys", "generate", "--out", str(tmp_path / "keys"), "--name", "ground1"]) == 0
    public, secret = tmp_path / "keys" / "ground1.key", tmp_path / "keys" / "ground1.key_secret"
    assert public.is_file() and stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert str(public) in capsys.readouterr().out
    zmq.auth.load_certificate(secret)
    assert main(["keys", "generate", "--out", str(tmp_path / "keys"), "--name", "ground1"]) == 1
    assert "--force" in capsys.readouterr().err
    assert main(["keys", "generate", "--out", str(tmp_path / "keys"), "--name", "ground1", "--force"]) == 0
    assert main(["keys", "generate", "--out", str(tmp_path / "keys"), "--name", "../x"]) == 1


def test_a_node_that_finished_its_job_is_silent_not_stale(ctx):
    """A replay's ingest ends after the final map: its last status says ``finished`` and the
    collector keeps its level (OK) however long ago it came; a node that just went silent is STALE."""
    with (
        DiagnosticsCollector(ctx, LOCAL, stale_after_s=0.3) as collector,
        Diagnostics(ctx, collector.endpoint, "ingest", period_s=0.01) as done,
        Diagnostics(ctx, collector.endpoint, "refiner", period_s=0.01) as silent,
    ):

        def both_seen():
            collector.poll(5)
            return {n["node"] for n in collector.nodes()} == {"ingest", "refiner"}

        assert wait_for(both_seen, step=lambda: (done.beat_now(0, "finished", {"finished": 1}), silent.beat(0)))
        time.sleep(0.6)
        collector.poll(5)
        levels = {n["node"]: n["level"] for n in collector.nodes()}
        assert levels == {"ingest": DiagnosticStatus.OK, "refiner": DiagnosticStatus.STALE}
