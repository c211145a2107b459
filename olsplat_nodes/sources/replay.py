"""Replay sources: an MCAP replay log or a folder of images + COLMAP model (``replay_log.read_replay``)."""

from __future__ import annotations

from pathlib import Path

from .base import PacedSource
from .replay_log import read_replay


class ReplaySource(PacedSource):
    """``read_replay(path)`` at the recorded pace, at ``rate_hz``, or as fast as asked (``fast``)."""

    kind = "replay"

    def __init__(self, path: str | Path, rate_hz: float | None = None, fast: bool = False, folder_rate_hz: float = 1.0):
        self.path = Path(path)
        super().__init__(read_replay(path, folder_rate_hz), rate_hz, fast)
