"""``urhead fit SUBJECT --out DIR``: fit an avatar to a subject in the VHAP layout."""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from urhead.config import FIT_PRESETS, FitConfig, add_arguments, from_arguments


def configure_threads(kernel_threads: int | None = None) -> None:
    """Rust kernels get ``kernel_threads`` (default: an explicit ``URHEAD_NUM_THREADS``,
    else every core); torch gets one thread. torch's OpenMP workers spin after each op and,
    on a small machine, starve the Rust pool (measured: up to 2× slower iterations on 2
    cores); the few torch ops of the loop are cheap single-threaded."""
    import torch

    if kernel_threads is None:
        os.environ.setdefault("URHEAD_NUM_THREADS", str(os.cpu_count() or 1))
    else:
        os.environ["URHEAD_NUM_THREADS"] = str(kernel_threads)
    torch.set_num_threads(1)


def add_fit_options(p: argparse.ArgumentParser) -> None:
    """The options that shape one fit, shared by ``fit`` and ``fit-many``."""
    p.add_argument(
        "--head",
        type=Path,
        default=None,
        help="head model .npz (urhead convert-flame output); default: the built-in procedural head",
    )
    p.add_argument("--preset", choices=sorted(FIT_PRESETS), default="paper")
    p.add_argument(
        "--test-last",
        type=int,
        default=None,
        help="hold out the last N timesteps of transforms.json instead of the split files",
    )
    add_arguments(p, FitConfig)


def fit_config(args: argparse.Namespace) -> FitConfig:
    """The fit's configuration from the options of :func:`add_fit_options`."""
    return from_arguments(FitConfig, args, FIT_PRESETS, args.preset)


def fit_subject(
    subject_dir: Path,
    out: Path,
    config: FitConfig,
    *,
    head_path: Path | None = None,
    test_last: int | None = None,
    resume: bool = False,
    progress: bool = True,
):
    """One fit of the subject in ``subject_dir`` into ``out``: what ``urhead fit`` runs, and
    what each ``fit-many`` task runs. Returns the trainer's ``FitResult``."""
    from urhead.data import load_subject
    from urhead.head import load_head, procedural_head
    from urhead.train.trainer import Trainer

    subject = load_subject(subject_dir, test_last=test_last)
    head = load_head(head_path) if head_path is not None else procedural_head(0)
    return Trainer(subject, head, config, out, progress=progress).run(resume=resume)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help="fit an avatar to a subject (VHAP / GaussianAvatars layout)",
        description="Fit a URHead avatar (FLAME mesh + UV-anchored Gaussians sharing UV maps) "
        "to a monocular subject. Writes DIR/avatar, DIR/metrics.json, DIR/psnr_vs_time.csv and "
        ".png, and DIR/checkpoint while running (continue with --resume).",
    )
    p.add_argument("subject", type=Path, help="subject folder (transforms*.json, images/, ...)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument(
        "--resume", action="store_true", help="continue from DIR/checkpoint if there is one"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_fit_options(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    config = fit_config(args)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    configure_threads()
    from tqdm.contrib.logging import logging_redirect_tqdm

    with logging_redirect_tqdm():  # log lines above the progress bar, not through it
        result = fit_subject(
            args.subject,
            args.out,
            config,
            head_path=args.head,
            test_last=args.test_last,
            resume=args.resume,
            progress=not args.quiet,
        )
    m = result.metrics
    print(
        f"held-out PSNR {m['psnr']:.2f} dB (mesh only {m['psnr_mesh_only']:.2f}), "
        f"SSIM {m['ssim']:.4f}, {m['num_gaussians']} Gaussians, {m['seconds']:.0f} s; "
        f"wrote {result.out / 'avatar'}"
    )
    return 0
