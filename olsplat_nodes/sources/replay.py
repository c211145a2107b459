"""Replay sources: an MCAP replay log, a folder of images + COLMAP model, or a ROS 2 bag
(``replay_log.read_replay``; ``bag``: the ``bag_*`` source params)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .base import WARN, PacedSource
from .replay_log import read_replay


class ReplaySource(PacedSource):
    """``read_replay(path)`` at the recorded pace, at ``rate_hz``, or as fast as asked (``fast``).
    A cut log's frames before the cut are replayed; then the status is WARN, saying so."""

    kind = "replay"

    def __init__(
        self,
        path: str | Path,
        rate_hz: float | None = None,
        fast: bool = False,
        folder_rate_hz: float = 1.0,
        bag: Mapping[str, Any] | None = None,
    ):
        self.path = Path(path)
        self.cut = ""  # what the reader said of a cut log or of a bag's pose-less frames ("" when none)
        super().__init__(read_replay(path, folder_rate_hz, self._on_cut, bag), rate_hz, fast)

    def _on_cut(self, message: str) -> None:
        self.cut = message

    def status(self) -> tuple[int, str]:
        return (WARN, self.cut) if self.done and self.cut else super().status()
