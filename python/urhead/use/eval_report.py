"""``urhead eval AVATAR``: image quality, temporal stability, speed and size of an avatar on
a subject's held-out frames (FORMATS.md "Evaluation protocol").

Metrics are on the subject's background (the avatar's ``background``), inside the frame's
head mask unless named ``*_full`` (the whole image, the convention of the INSTA / URHead
tables): PSNR and SSIM (:mod:`urhead.losses`), PSNR of the mesh branch alone,
LPIPS-alex / LPIPS-vgg when their weights are on disk (:mod:`urhead.eval.lpips`),
ST-LPIPS-alex (``stlpips_alex``, shift-tolerant LPIPS from the weights the
``stlpips-pytorch`` wheel ships, :mod:`urhead.eval.stlpips`; lower is better). Held-out
frames are scored with their tracked FLAME parameters; with ``--refine-flame`` also after
test-time refinement of each held-out frame's FLAME row against the frozen avatar
(``psnr_refined``, ``psnr_refined_full``, ``ssim_refined``; :mod:`urhead.eval.refine`).

Temporal stability, over consecutive frame pairs (same camera, timesteps t−1 and t):
- ``temporal_error_change``: the mean absolute change of the signed error image,
  |(Î_t − I_t) − (Î_{t−1} − I_{t−1})|, inside both frames' masks. Flicker the ground truth
  does not have raises it; an avatar whose error is steady keeps it low. Always reported.
- ``temporal_lpips_<variant>``: |LPIPS(Î_t, Î_{t−1}) − LPIPS(I_t, I_{t−1})|, how much more
  (or less) the rendering changes perceptually between frames than the video does; only
  with LPIPS weights.
- ``temporal_stlpips_alex``: the same with ST-LPIPS.
Each is reported as mean and variance over the pairs.

With ``--error-breakdown``, ``error_breakdown`` says where the in-mask error sits: its share
and PSNR in the silhouette band, beyond the mesh and on it, per head region
(:mod:`urhead.eval.breakdown`), after refinement when ``--refine-flame`` is given.

Speed: the median over frames of one forward render (no gradients, after one warm-up
render), as frames per second, at the subject's resolution.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import torch

from urhead._atomic import write_file_atomically
from urhead._progress import progress as progress_bar
from urhead.eval import RefineSettings, evaluate_frames, refine_params_of
from urhead.eval.breakdown import error_breakdown, format_breakdown
from urhead.eval.metrics import frame_params
from urhead.eval.per_frame import (
    FLAME_PARAMETERS,
    METRIC_REGION,
    mean,
    score_frames,
    variance,
)
from urhead.use.common import (
    add_background_option,
    check_output_file,
    open_avatar,
    open_subject,
    split_frames,
    use_background,
)

TEMPORAL_KEYS = (
    "temporal_error_change",
    "temporal_lpips_alex",
    "temporal_lpips_vgg",
    "temporal_stlpips_alex",
)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="score an avatar on a subject's held-out frames",
        description="PSNR, SSIM, LPIPS (alex, vgg: only when their weight files are on "
        "disk, see --lpips-weights), temporal stability, rendering FPS and Gaussian count "
        "of an avatar, inside the head mask on the subject's background. Prints a table "
        "and writes JSON (default AVATAR/eval_SPLIT.json).",
    )
    p.add_argument("avatar", type=Path, help="avatar directory (the fit's OUT/avatar)")
    p.add_argument(
        "--subject",
        type=Path,
        default=None,
        help="subject folder (default: the one the fit recorded)",
    )
    p.add_argument(
        "--split", choices=("test", "val", "train"), default="test", help="frames to score"
    )
    p.add_argument(
        "--lpips-weights",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder with alex.pth/vgg.pth (lpips v0.1) and alexnet*.pth/vgg16*.pth "
        "(torchvision); default $URHEAD_LPIPS_DIR, then ~/.cache/urhead/lpips",
    )
    p.add_argument(
        "--json",
        default=None,
        metavar="FILE",
        help="where to write the JSON, '-' for standard output (the table then goes to "
        "standard error); default: AVATAR/eval_SPLIT.json",
    )
    p.add_argument(
        "--no-stlpips",
        action="store_true",
        help="skip ST-LPIPS (about 3 s per frame at 512² on 2 cores)",
    )
    p.add_argument(
        "--refine-flame",
        action="store_true",
        help="also score after refining each held-out frame's FLAME row against the frozen "
        "avatar (reported as psnr_refined, psnr_refined_full, ssim_refined)",
    )
    p.add_argument(
        "--refine-steps",
        type=int,
        default=RefineSettings().steps,
        help="Adam steps per frame at <= 256 px for --refine-flame (default: %(default)s)",
    )
    p.add_argument(
        "--refine-full-steps",
        type=int,
        default=RefineSettings().full_steps,
        help="Adam steps per frame at full size after --refine-steps (default: %(default)s)",
    )
    p.add_argument(
        "--refine-coarse-max-steps",
        type=int,
        default=RefineSettings().coarse_max_steps,
        help="let the <= 256 px stage go on past --refine-steps, up to this many, while a "
        f"step still lowers the loss by {RefineSettings().coarse_min_gain:.0%}% (for trackers "
        "several pixels off; default: %(default)s, off)",
    )
    p.add_argument(
        "--error-breakdown",
        action="store_true",
        help="also report where the in-mask error sits: the silhouette band, mask pixels "
        "beyond the mesh and the rest, per head region (after refinement with "
        "--refine-flame); one more render per frame",
    )
    add_background_option(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from urhead.eval.lpips import load_lpips
    from urhead.eval.stlpips import load_stlpips

    opened = open_avatar(args.avatar)
    to_stdout = args.json == "-"
    if not to_stdout:
        out = check_output_file(
            Path(args.json) if args.json is not None else opened.path / f"eval_{args.split}.json",
            "--json",
            ".json",
        )
    report = sys.stderr if to_stdout else sys.stdout  # standard output holds only the JSON
    subject = open_subject(opened, args.subject)
    use_background(opened, subject, args.background)
    frames = split_frames(subject, args.split)
    nets, notes = load_lpips(args.lpips_weights)
    stlpips = None
    if not args.no_stlpips:
        stlpips, note = load_stlpips()
        notes += [note] if note else []
    for note in notes:
        print(note, file=report)
    for name in ("refine_steps", "refine_full_steps", "refine_coarse_max_steps"):
        if getattr(args, name) < 0:
            raise SystemExit(f"--{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}")
    refine = (
        RefineSettings(
            steps=args.refine_steps,
            full_steps=args.refine_full_steps,
            coarse_max_steps=args.refine_coarse_max_steps,
        )
        if args.refine_flame
        else None
    )
    result = evaluate_avatar(
        opened.avatar,
        frames,
        occlusion_aware=opened.occlusion_aware,
        lpips=nets,
        stlpips=stlpips,
        refine=refine,
        breakdown=args.error_breakdown,
        progress=True,
    )
    result.update(
        avatar=str(opened.path),
        subject=str(subject.root),
        split=args.split,
        lpips_skipped=notes,
    )
    text = json.dumps(result, indent=2)
    print(format_table(result), file=report)
    if result.get("error_breakdown") is not None:
        print(format_breakdown(result["error_breakdown"]), file=report)
    if to_stdout:
        print(text, flush=True)
    else:
        write_file_atomically(out, lambda tmp: tmp.write_text(text))
        print(f"wrote {out}")
    return 0


def evaluate_avatar(
    avatar,
    frames,
    *,
    occlusion_aware: bool = True,
    lpips=None,
    stlpips=None,
    refine: RefineSettings | None = None,
    breakdown: bool = False,
    progress: bool = False,
) -> dict:
    """Scores ``frames`` (dataset frames with image, mask, camera, flame); ``lpips`` maps a
    variant name ("alex", "vgg") to a scorer ``(image, target, mask) -> float``;
    ``stlpips`` is a :class:`~urhead.eval.stlpips.StLpips` or None; with ``refine`` also
    after test-time refinement; with ``breakdown`` also ``error_breakdown`` (of the
    refined parameters when refining). Returns the JSON-ready metrics (module
    docstring)."""
    if len(frames) == 0:
        raise ValueError("frames is empty: nothing to evaluate")
    result = _evaluate(
        avatar,
        frames,
        occlusion_aware=occlusion_aware,
        lpips=lpips or {},
        stlpips=stlpips,
        progress=progress,
    )
    refined = None
    if refine is not None and refine.total_steps > 0:
        with progress_bar(len(frames), "refine", enabled=progress) as bar:
            refined = refine_params_of(
                avatar, frames, refine, occlusion_aware, progress=lambda: bar.update(1)
            )
        after = evaluate_frames(
            avatar, frames, occlusion_aware=occlusion_aware, mesh_only=False, params=refined
        )
        result.update(
            psnr_refined=after.psnr,
            psnr_refined_full=after.psnr_full,
            ssim_refined=after.ssim,
            refine_steps=refine.steps,
            refine_full_steps=refine.full_steps,
        )
        result["per_frame"]["psnr_refined"] = list(after.per_frame_psnr)
    result["error_breakdown"] = None
    if breakdown:
        params = refined or [frame_params(avatar, frame) for frame in frames]
        result["error_breakdown"] = error_breakdown(
            avatar, frames, params, occlusion_aware=occlusion_aware
        )
        result["error_breakdown"]["flame_parameters"] = "tracked" if refined is None else "refined"
    return result


@torch.no_grad()
def _evaluate(
    avatar, frames, *, occlusion_aware: bool, lpips: dict, stlpips, progress: bool
) -> dict:
    params = [frame_params(avatar, frame) for frame in frames]
    first = frames[0]
    avatar.render(params[0], first.camera, occlusion_aware=occlusion_aware)  # warm-up
    per = score_frames(
        avatar,
        frames,
        params,
        occlusion_aware=occlusion_aware,
        mesh_only=True,
        perceptual={f"lpips_{v}": net for v, net in lpips.items()},
        stlpips=stlpips,
        temporal=True,
        progress=progress,
    )
    median = statistics.median(per.seconds)
    result = {
        "frames": len(frames),
        "psnr": mean(per.psnr),
        "psnr_full": mean(per.psnr_full),
        "psnr_refined": None,
        "psnr_refined_full": None,
        "ssim": mean(per.ssim),
        "ssim_refined": None,
        "psnr_mesh_only": mean(per.psnr_mesh_only),
    }
    for v in ("alex", "vgg"):
        result[f"lpips_{v}"] = mean(per.perceptual.get(f"lpips_{v}", []))
    result["stlpips_alex"] = mean(per.stlpips_alex)
    for key in TEMPORAL_KEYS:
        values = per.temporal.get(key, [])
        result[f"{key}_mean"] = mean(values)
        result[f"{key}_var"] = variance(values)
    result["temporal_pairs"] = len(per.temporal["temporal_error_change"])
    result.update(
        render_fps=1.0 / median,
        render_ms_median=1000.0 * median,
        resolution=[first.camera.width, first.camera.height],
        num_gaussians=avatar.num_gaussians,
        metric_region=METRIC_REGION,
        flame_parameters=FLAME_PARAMETERS,
        background=avatar.background.tolist(),
        per_frame={
            "timestep": per.timesteps,
            "psnr": per.psnr,
            "ssim": per.ssim,
            "stlpips_alex": per.stlpips_alex if stlpips is not None else None,
        },
    )
    return result


def format_table(r: dict) -> str:
    def fmt(v, spec, missing="skipped"):
        return missing if v is None else format(v, spec)

    rows = [
        ("frames", str(r["frames"])),
        ("PSNR in mask (dB)", fmt(r["psnr"], ".3f")),
        ("PSNR full image (dB)", fmt(r["psnr_full"], ".3f")),
        ("PSNR refined, in mask (dB)", fmt(r["psnr_refined"], ".3f", "off (--refine-flame)")),
        (
            "PSNR refined, full image (dB)",
            fmt(r["psnr_refined_full"], ".3f", "off (--refine-flame)"),
        ),
        ("SSIM", fmt(r["ssim"], ".4f")),
        ("PSNR mesh only (dB)", fmt(r["psnr_mesh_only"], ".3f")),
        ("LPIPS alex", fmt(r["lpips_alex"], ".4f")),
        ("LPIPS vgg", fmt(r["lpips_vgg"], ".4f")),
        ("ST-LPIPS alex", fmt(r.get("stlpips_alex"), ".4f")),
        (
            "temporal error change",
            f"{fmt(r['temporal_error_change_mean'], '.5f')} "
            f"(var {fmt(r['temporal_error_change_var'], '.2e')}, {r['temporal_pairs']} pairs)",
        ),
    ]
    for key, name in (
        ("temporal_lpips_alex", "temporal LPIPS alex"),
        ("temporal_lpips_vgg", "temporal LPIPS vgg"),
        ("temporal_stlpips_alex", "temporal ST-LPIPS alex"),
    ):
        if r.get(f"{key}_mean") is not None:
            rows.append((name, f"{r[f'{key}_mean']:.5f} (var {r[f'{key}_var']:.2e})"))
    w, h = r["resolution"]
    rows += [
        (f"render FPS ({w}×{h})", f"{r['render_fps']:.1f} ({r['render_ms_median']:.1f} ms median)"),
        ("Gaussians", str(r["num_gaussians"])),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    return "\n".join([f"{r['split']} split, {r['metric_region']}", *lines])
