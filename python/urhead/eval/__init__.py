"""Evaluating an avatar against held-out frames (FORMATS.md "Evaluation protocol")."""

from urhead.eval.metrics import (
    FrameScores,
    evaluate_frames,
    exact_flame_scores,
    refine_params_of,
)
from urhead.eval.refine import RefineSettings, refine_params, refine_sequence

__all__ = [
    "FrameScores",
    "RefineSettings",
    "evaluate_frames",
    "exact_flame_scores",
    "refine_params",
    "refine_params_of",
    "refine_sequence",
]
