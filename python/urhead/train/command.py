"""``urhead fit SUBJECT --out DIR``: fit an avatar to a subject in the VHAP layout."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from urhead.config import FIT_PRESETS, FitConfig, add_arguments, from_arguments
from urhead.errors import InvalidArgumentError


def add_fit_options(p: argparse.ArgumentParser) -> None:
    """The options that shape one fit, shared by ``fit`` and ``fit-many``."""
    p.add_argument(
        "--head",
        type=Path,
        default=None,
        help="head model .npz (urhead convert-flame output); default: the built-in procedural head",
    )
    p.add_argument(
        "--preset",
        choices=sorted(FIT_PRESETS),
        default="paper",
        help="schedule and resolution: the paper's, or quick (minutes on 2 cores); an "
        "option below overrides its preset value",
    )
    p.add_argument(
        "--test-last",
        type=int,
        default=None,
        help="hold out the last N timesteps of transforms.json instead of the split files",
    )
    add_arguments(p, FitConfig, FIT_PRESETS)


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
    force: bool = False,
    progress: bool = True,
):
    """One fit of the subject in ``subject_dir`` into ``out``: what ``urhead fit`` runs, and
    what each ``fit-many`` task runs. Returns the trainer's ``FitResult``. Everything is
    checked before the work: the memory the maps need, ``out`` free of another running fit
    (locked for this one) and of a finished fit (unless ``resume`` or ``force``), the
    subject and the head."""
    from urhead._atomic import folder_lock, remove_stale_temporaries
    from urhead.data import load_subject
    from urhead.head import load_head, procedural_head
    from urhead.train.memory import check_fit_memory
    from urhead.train.trainer import Trainer
    from urhead.use.common import add_subject_record

    check_fit_memory(config)
    out = Path(out)
    finished = out / "avatar" / "avatar.json"
    if finished.is_file() and not (resume or force):
        raise InvalidArgumentError(
            f"--out {out}: holds a finished fit ({finished.parent}); pass --force to "
            "replace it, or choose another --out"
        )
    subject = load_subject(subject_dir, test_last=test_last)
    head = load_head(head_path) if head_path is not None else procedural_head(0)
    trainer = Trainer(subject, head, config, out, progress=progress)  # checks the background
    with folder_lock(out, "--out"):  # created only once the inputs are known to be good
        remove_stale_temporaries(out)
        result = trainer.run(resume=resume)
        # The trainer records the subject's absolute path; the relative one lets an avatar
        # moved together with its subject find it.
        add_subject_record(result.out / "avatar", subject.root)
    return result


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
    p.add_argument(
        "--force", action="store_true", help="replace a finished fit in DIR (else an error)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_fit_options(p)
    p.set_defaults(run=run, resume_hint=resume_hint)


def resume_hint(args: argparse.Namespace) -> str:
    """What Ctrl-C leaves behind and how to continue from it."""
    from urhead.train.checkpoint import find_checkpoint

    found = find_checkpoint(Path(args.out))
    if found is None:
        return "No checkpoint was written yet; run the same command again to start over."
    return f"The last checkpoint is {found}; continue with the same command and --resume."


def run(args: argparse.Namespace) -> int:
    config = fit_config(args)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from tqdm.contrib.logging import logging_redirect_tqdm

    with logging_redirect_tqdm():  # log lines above the progress bar, not through it
        result = fit_subject(
            args.subject,
            args.out,
            config,
            head_path=args.head,
            test_last=args.test_last,
            resume=args.resume,
            force=args.force,
            progress=not args.quiet,
        )
    m = result.metrics
    print(
        f"held-out PSNR {m['psnr']:.2f} dB in the mask ({m['psnr_full']:.2f} full image; "
        f"after test-time refinement {_db(m['psnr_refined'])} / {_db(m['psnr_refined_full'])}), "
        f"mesh only {m['psnr_mesh_only']:.2f}, SSIM {m['ssim']:.4f}, {m['num_gaussians']} "
        f"Gaussians, {m['seconds']:.0f} s; wrote {result.out / 'avatar'}"
    )
    return 0


def _db(value) -> str:
    return "off" if value is None else f"{value:.2f}"
