"""Evaluating an avatar against held-out frames (FORMATS.md "Evaluation protocol")."""

from urhead.eval.metrics import FrameScores, evaluate_frames

__all__ = ["FrameScores", "evaluate_frames"]
