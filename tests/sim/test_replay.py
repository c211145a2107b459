"""``olsplat sim replay``: a simulated flight's log printed at its pace; a missing log fails clearly."""

from __future__ import annotations

from olsplat_nodes.cli import main


def test_replay_cli(tiny, capsys, tmp_path):
    out, _ = tiny
    assert main(["sim", "replay", "--log", str(out / "replay.mcap"), "--fast", "--limit", "3"]) == 0
    printed = capsys.readouterr().out
    assert "frame_0002.jpg" in printed and "3 frames in" in printed
    assert main(["sim", "replay", "--log", str(tmp_path / "missing.mcap"), "--fast"]) == 1
    assert "missing.mcap: does not exist" in capsys.readouterr().err
    assert main(["sim", "replay", "--log", str(out / "replay.mcap"), "--rate", "0"]) == 1
    assert "rate must be positive" in capsys.readouterr().err
