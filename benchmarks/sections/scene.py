"""The scene the whole-iteration and rendering sections measure: a real avatar at the
paper's settings (2048² maps, SH degree 3, 512² images, ~24k Gaussians) on the built-in
procedural head, built by the trainer from a few frames of a synthetic subject."""

from __future__ import annotations

import tempfile
from dataclasses import replace
from functools import lru_cache
from pathlib import Path

from urhead.config import FitConfig
from urhead.data import load_subject
from urhead.data.synth.subject import SynthConfig, synthesize
from urhead.head import procedural_head
from urhead.train.trainer import Trainer

ROOT = Path(__file__).resolve().parents[2]
SUBJECT = SynthConfig(frames=6, resolution=512, samples_per_side=1, edge_samples_per_side=2)


@lru_cache(maxsize=2)
def paper_scene(num_gaussians: int = 24_000, uv_resolution: int = 2048):
    """``(trainer, state)`` ready for :meth:`Trainer.step`, at the paper's settings with
    ``num_gaussians`` Gaussians (the budget held there: no sampling during timing)."""
    subject_dir = synthesize(ROOT / ".cache" / "bench_subject", SUBJECT, progress=False)
    config = replace(
        FitConfig(),
        uv_resolution=uv_resolution,
        initial_gaussians=num_gaussians,
        max_gaussians=num_gaussians,
        color_init_frames=1,
        iterations=10**9,
        checkpoint_every=10**9,
        eval_every_seconds=1e12,
    )
    out = Path(tempfile.mkdtemp(prefix="urhead-bench-"))
    trainer = Trainer(load_subject(subject_dir), procedural_head(0), config, out, progress=False)
    return trainer, trainer.start()
