"""Capture conditions × remedies: what each real-capture condition (tracking error, light
fixed in the room, hair off the FLAME surface) costs the avatar, measured against its
oracle (the same subject without the condition), and how much of it each remedy wins back.

Subjects are the built-in synthetic one at 256², 300 frames (210 train / 90 held out), with
one condition changed at a time (`urhead synth --tracking-noise / --light / --hair`).
Remedies are cumulative settings of the quick preset, from the paper's model (the quick
preset as it was before them) to today's quick preset. Every fit is the real trainer; the
held-out frames are never used for anything but the score. A fit's result is cached in
``.cache/conditions/`` under a key of its subject, its settings and the code that fitted it
(urhead's Python sources and native module), so a long run can be resumed and the markdown
rebuilt without refitting, and a change to the model or a kernel refits.
"""

from __future__ import annotations

import datetime
import hashlib
import json
from dataclasses import asdict, replace
from pathlib import Path

import urhead
from sections.common import one_torch_thread, table
from urhead.config import FIT_PRESETS, FitConfig
from urhead.data import load_subject
from urhead.data.synth.subject import SynthConfig, synthesize
from urhead.head import procedural_head
from urhead.train.trainer import Trainer

TITLE = "Capture conditions and their remedies"
ROOT = Path(__file__).resolve().parents[2]
CACHE = ROOT / ".cache" / "conditions"
RESOLUTION = 256

SUBJECTS = {
    # name: (SynthConfig overrides, what it isolates)
    "default": ({}, "soft light, short hair (shell), ~1 px tracking error"),
    "oracle: exact tracking": ({"tracking_noise": 0.0}, "default without tracking error"),
    "oracle: no hair": ({"hair": "none"}, "default without hair off the surface"),
    "oracle: flat light": ({"light": "flat"}, "default under even light"),
    "key light": ({"light": "key"}, "default under a hard key light"),
    "hair strands": ({"hair": "strands"}, "default with 2500 strands"),
    "hard": ({"difficulty": "hard"}, "key light, strands, ~4 px tracking error"),
}

PAPER_MODEL = {
    "lr_pose": 1e-5,
    "lr_translation": 1e-6,
    "gaussian_offset": False,
    "lambda_alpha": 0.0,
}
"""The paper's model and FLAME rates on the quick preset's schedule (no offset map E, no
silhouette term; what the quick preset was before the remedies); test-time refinement is
still scored, so its gain shows alone."""

REMEDIES = {"paper model": PAPER_MODEL, "quick preset": {}}
"""Overrides of today's quick preset."""

RUNS = [(subject, remedy) for subject in SUBJECTS for remedy in REMEDIES]
"""Every subject under every remedy: what each condition costs and what the remedies win
back (each fit ~4-6 min at 256² on 2 cores)."""

CONDITIONS = [
    # (condition, subject with it, its oracle)
    ("tracking error (~1 px)", "default", "oracle: exact tracking"),
    ("hair shell off the surface", "default", "oracle: no hair"),
    ("soft light fixed in the room", "default", "oracle: flat light"),
    ("hard key light fixed in the room", "key light", "oracle: flat light"),
    ("hair strands instead of a shell", "hair strands", "oracle: no hair"),
]
"""Each condition's cost: the oracle's score minus the subject's (the oracle differs from
the subject in that condition only)."""


def subject_config(name: str) -> SynthConfig:
    return SynthConfig(frames=300, resolution=RESOLUTION, **SUBJECTS[name][0])


def fit_config(remedy: str) -> FitConfig:
    # The quick preset as the main job runs it (no periodic held-out log: it is not scored).
    base = replace(FitConfig(), **{**FIT_PRESETS["quick"], "eval_every_seconds": 1e9})
    return replace(base, **REMEDIES[remedy])


def _code_fingerprint() -> str:
    """SHA-256 of the installed urhead package: its Python sources and native module."""
    package = Path(urhead.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*")):
        if path.suffix in (".py", ".so", ".pyd") and path.is_file():
            digest.update(str(path.relative_to(package)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def _key(subject: SynthConfig, config: FitConfig) -> str:
    blob = json.dumps(
        {"subject": subject.cache_key(), "fit": asdict(config), "code": _code_fingerprint()},
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def fit_once(subject_name: str, remedy: str) -> dict:
    """The scores of one (subject, remedy) fit, from the cache when it was made before."""
    from urhead.eval import exact_flame_scores

    synth, config = subject_config(subject_name), fit_config(remedy)
    cached = CACHE / f"{_key(synth, config)}.json"
    if cached.is_file():
        return json.loads(cached.read_text())
    folder = synthesize(ROOT / ".cache" / "subjects" / synth.cache_key(), synth, progress=False)
    subject = load_subject(folder)
    out = CACHE / f"{_key(synth, config)}.fit"
    result = Trainer(subject, procedural_head(0), config, out, progress=False).run()
    oracle = exact_flame_scores(
        result.avatar, list(subject.test), folder / "synthetic_ground_truth.npz"
    )
    m = result.metrics
    scores = {
        key: m[key]
        for key in (
            "psnr",
            "psnr_full",
            "psnr_refined",
            "psnr_refined_full",
            "psnr_mesh_only",
            "ssim",
            "num_gaussians",
            "seconds",
            "evaluation_seconds",
        )
    }
    scores.update(
        measured=datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        psnr_exact_flame=oracle.psnr,
        psnr_exact_flame_full=oracle.psnr_full,
        subject=subject_name,
        remedy=remedy,
    )
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = cached.with_suffix(".tmp")
    tmp.write_text(json.dumps(scores, indent=1))
    tmp.replace(cached)
    return scores


def run(quick: bool) -> dict:
    with one_torch_thread():
        runs = RUNS[:2] if quick else RUNS
        results = []
        for subject_name, remedy in runs:
            print(f"   {subject_name} × {remedy}", flush=True)
            results.append(fit_once(subject_name, remedy))
        return {"resolution": RESOLUTION, "runs": results}


def _cell(r: dict | None, key: str) -> str:
    return "—" if r is None or r.get(key) is None else f"{r[key]:.2f}"


def _when(runs: list[dict]) -> str:
    """Which rows were measured after the section's date (added to a stored report by
    fitting only them, the code unchanged in what it computes)."""
    later = [r for r in runs if r.get("measured")]
    if not later:
        return ""
    dates = sorted({r["measured"] for r in later})
    names = ", ".join(f"{r['subject']} × {r['remedy']}" for r in later)
    return f" Rows {names} were measured {dates[0]} to {dates[-1]}."


def render(results: dict, figures: Path) -> str:
    runs = {(r["subject"], r["remedy"]): r for r in results["runs"]}
    remedy_rows = []
    for remedy in REMEDIES:
        r = runs.get(("default", remedy))
        remedy_rows.append(
            [remedy]
            + [_cell(r, k) for k in ("psnr", "psnr_full", "psnr_refined", "psnr_refined_full")]
            + [_cell(r, "psnr_mesh_only"), "—" if r is None else f"{r['seconds']:.0f}"]
        )
    first, last = "paper model", "quick preset"
    subject_rows = []
    for name, (_, what) in SUBJECTS.items():
        for remedy in REMEDIES:
            r = runs.get((name, remedy))
            if r is None:
                continue  # not measured in this report
            keys = ("psnr", "psnr_full", "psnr_refined", "psnr_refined_full")
            keys += ("psnr_exact_flame", "psnr_mesh_only")
            subject_rows.append([name, what, remedy, *(_cell(r, k) for k in keys)])
    gains = []
    for name in SUBJECTS:
        a, b = runs.get((name, first)), runs.get((name, last))
        if a is None or b is None:
            continue
        keys = ("psnr", "psnr_full", "psnr_refined", "psnr_refined_full")
        gains.append([name, *(f"{b[k] - a[k]:+.2f}" for k in keys)])
    costs = []
    for condition, subject, oracle in CONDITIONS:
        row = [condition, subject, oracle]
        for remedy in (first, last):
            d, o = runs.get((subject, remedy)), runs.get((oracle, remedy))
            for key in ("psnr", "psnr_refined"):
                row.append("—" if d is None or o is None else f"{o[key] - d[key]:.2f}")
        costs.append(row)
    quick = FIT_PRESETS["quick"]
    return "\n\n".join(
        [
            f"Synthetic subjects at {results['resolution']}², 300 frames (210 train, 90 held "
            f"out), the quick preset ({quick['iterations']} iterations, "
            f"{quick['uv_resolution']}² maps). PSNR in dB "
            "on the held-out frames: `psnr` inside the mask with the tracked FLAME parameters, "
            "`_full` on the whole image, `refined` after test-time refinement of each held-out "
            f"frame's FLAME row against the frozen avatar ({quick['refine_steps']} steps at "
            f"≤ 256 px, then {quick['refine_full_steps']} at full size), `exact FLAME` with the "
            "subject's true parameters (an oracle only a synthetic subject has). One fit per "
            "row (seed 0)." + _when(results["runs"]),
            "**The remedies on the default subject** (paper model: the paper's FLAME rates, "
            "no offset map, no silhouette term; both with test-time refinement scored):",
            table(
                [
                    "model",
                    "psnr",
                    "psnr_full",
                    "psnr_refined",
                    "psnr_refined_full",
                    "mesh only",
                    "train s",
                ],
                remedy_rows,
            ),
            "**Each condition × remedy** (the paper model and today's quick preset on every "
            "subject; in the mask and on the full image):",
            table(
                [
                    "subject",
                    "what",
                    "model",
                    "psnr",
                    "psnr_full",
                    "psnr_refined",
                    "psnr_refined_full",
                    "exact FLAME",
                    "mesh only",
                ],
                subject_rows,
            ),
            "**What the remedies win** (quick preset minus paper model, dB, per subject):",
            table(["subject", "psnr", "psnr_full", "psnr_refined", "psnr_refined_full"], gains),
            "**What each condition still costs** (oracle minus subject, dB; in-mask):",
            table(
                [
                    "condition",
                    "subject",
                    "oracle",
                    "paper: psnr",
                    "paper: refined",
                    "quick: psnr",
                    "quick: refined",
                ],
                costs,
            ),
        ]
    )
