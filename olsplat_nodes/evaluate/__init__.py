"""Metrics (mIoU, mAcc, Loc@40/50/60) and scene evaluation of language maps."""

from .metrics import QueryScore, summarize
from .scene_eval import evaluate_map

__all__ = ["QueryScore", "evaluate_map", "summarize"]
