"""The main job: make the built-in synthetic subject (a ray-traced procedural head, 300
frames at 512², cached) and fit a URHead avatar to it with the ``quick`` preset, then score
it on the held-out frames.

    python examples/fit_subject.py [--out DIR] [--subject DIR] [--preset quick|paper]

Writes into DIR (default ``outputs/fit_subject``): ``avatar/`` (the avatar directory),
``metrics.json``, ``psnr_vs_time.csv`` / ``.png`` (held-out PSNR against training time) and
``test_frames.png`` (held-out frames, labelled: ground truth | avatar with the tracked FLAME
parameters | avatar after test-time refinement | mesh branch alone | error ×4).
On the built-in subject ``metrics.json`` also has ``psnr_true_flame`` (``_full``): the
held-out PSNR with the subject's exact FLAME parameters instead of the tracked ones.
With ``--subject`` it fits that subject instead of making the built-in one.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm.contrib.logging import logging_redirect_tqdm

from urhead._atomic import write_bytes_atomically, write_file_atomically
from urhead._memory import keep_freed_memory
from urhead._threads import configure_threads
from urhead.config import FIT_PRESETS, FitConfig
from urhead.data import load_subject
from urhead.data.images import to_uint8, write_png
from urhead.data.synth.subject import SynthConfig, synthesize
from urhead.eval import exact_flame_scores
from urhead.eval.metrics import frame_params
from urhead.head import procedural_head
from urhead.train.trainer import Trainer

BUILT_IN_SUBJECT = SynthConfig(frames=300)
"""300 frames (210 train, 90 held out): enough motion for the fit, made in ~2.5 minutes."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("outputs/fit_subject"))
    parser.add_argument("--subject", type=Path, default=None, help="fit this subject instead")
    parser.add_argument("--preset", choices=sorted(FIT_PRESETS), default="quick")
    parser.add_argument("--iterations", type=int, default=None, help="override the preset")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted fit")
    args = parser.parse_args()
    configure_threads()
    keep_freed_memory()
    start = time.perf_counter()
    subject_dir = args.subject
    if subject_dir is None:
        subject_dir = args.out / "subject"
        print(f"built-in subject: {subject_dir} (reused when already made)")
        synthesize(subject_dir, BUILT_IN_SUBJECT)
    subject = load_subject(subject_dir)
    config = replace(FitConfig(), **FIT_PRESETS[args.preset])
    if args.iterations is not None:
        config = replace(config, iterations=args.iterations)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with logging_redirect_tqdm():  # log lines above the progress bar, not through it
        result = Trainer(subject, procedural_head(0), config, args.out).run(resume=args.resume)
    write_test_strip(result, subject, args.out / "test_frames.png", config)
    metrics = dict(result.metrics, total_seconds=round(time.perf_counter() - start, 1))
    truth = subject_dir / "synthetic_ground_truth.npz"
    if truth.is_file():
        oracle = exact_flame_scores(result.avatar, held_out(subject), truth)
        metrics["psnr_true_flame"] = oracle.psnr
        metrics["psnr_true_flame_full"] = oracle.psnr_full
    write_bytes_atomically(args.out / "metrics.json", json.dumps(metrics, indent=2).encode())
    print(json.dumps(metrics, indent=2))
    print(f"wrote {args.out}/avatar, metrics.json, psnr_vs_time.png, test_frames.png")


def held_out(subject):
    return subject.test if len(subject.test) else subject.val


def write_test_strip(result, subject, path: Path, config: FitConfig, count: int = 4) -> None:
    """Rows of held-out frames, labelled: ground truth | avatar (tracked FLAME) | avatar
    (refined FLAME) | mesh branch (tracked) | error ×4 (refined). The refined parameters
    are the ones the fit's metrics were scored with (refined again only if it has none)."""
    import cv2

    from urhead.eval import RefineSettings, refine_params_of

    avatar = result.avatar
    frames = held_out(subject)
    picks = np.linspace(0, len(frames) - 1, count).round().astype(int)
    shown = [frames[int(i)] for i in picks]
    scored = [result.refined.get((f.timestep, f.camera_index)) for f in shown]
    if any(p is None for p in scored):
        settings = RefineSettings(steps=config.refine_steps, full_steps=config.refine_full_steps)
        scored = refine_params_of(avatar, shown, settings)
    rows = []
    for frame, refined in zip(shown, scored, strict=True):
        tracked = frame_params(avatar, frame)
        with torch.no_grad():
            out = avatar.render(tracked, frame.camera)
            better = avatar.render(refined, frame.camera).image.clamp(0, 1)
        error = ((better - frame.image).abs() * 4).clamp(0, 1)
        tiles = [frame.image, out.image.clamp(0, 1), better, out.mesh.image.clamp(0, 1), error]
        rows.append(torch.cat(tiles, 1))
    image = to_uint8(torch.cat(rows, 0).numpy())
    tile = frames[0].camera.width
    labels = ["ground truth", "avatar, tracked FLAME", "avatar, refined FLAME", "mesh branch"]
    labels.append("error x4 (refined)")
    scale = max(tile / 512, 0.35)
    for k, label in enumerate(labels):
        org = (k * tile + int(8 * scale), int(24 * scale))
        cv2.putText(image, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (0, 0, 0), 3)
        cv2.putText(image, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (255, 255, 255), 1)
    write_file_atomically(path, lambda tmp: write_png(tmp, image))


if __name__ == "__main__":
    main()
