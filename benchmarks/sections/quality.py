"""Quality against time on the built-in subject: held-out PSNR against training wall-clock
seconds for UV resolutions, SH degrees, Gaussian budgets, adaptive vs uniform sampling and
the paper's ablations, plus what leaving out pays (time per iteration and map memory).

Every run is the real trainer on the built-in synthetic subject (examples/fit_subject.py's,
300 frames at 512²) from the quick preset with a shorter schedule, so the curves compare
settings at equal cost, not converged quality. One run at a time, 2 cores, torch on one
thread as the trainer configures it.
"""

from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

from sections.common import one_torch_thread, save, table
from urhead.config import FIT_PRESETS, FitConfig
from urhead.data import load_subject
from urhead.data.synth.subject import SynthConfig, synthesize
from urhead.head import procedural_head
from urhead.model import MapLayout
from urhead.train.trainer import Trainer

TITLE = "Quality against time on the built-in subject"
ROOT = Path(__file__).resolve().parents[2]
SUBJECT = SynthConfig(frames=300, difficulty="hard")
"""Measured on the subject that was the built-in one before the capture conditions (now
``--difficulty hard``); the "Capture conditions" section covers today's default."""

# (group, name, overrides of the quick preset)
RUNS = [
    ("uv resolution", "512² maps (quick preset)", {}),
    ("uv resolution", "256² maps", {"uv_resolution": 256}),
    ("uv resolution", "1024² maps", {"uv_resolution": 1024}),
    ("uv resolution", "2048² maps", {"uv_resolution": 2048}),
    ("sh degree", "SH 0", {"sh_degree": 0}),
    ("sh degree", "SH 1", {"sh_degree": 1}),
    ("gaussian budget", "budget 5k", {"initial_gaussians": 3_000, "max_gaussians": 5_000}),
    ("gaussian budget", "budget 30k", {"initial_gaussians": 10_000, "max_gaussians": 30_000}),
    ("sampling", "uniform sampling", {"sampling": "uniform"}),
    ("ablation", "mesh only", {"gaussians": False}),
    ("ablation", "no normal loss", {"normal_loss": False}),
    ("ablation", "no occlusion-aware blending", {"occlusion_aware": False}),
    ("ablation", "no 0.2 mesh term", {"mesh_term": 0.0}),
]
BASE = RUNS[0][1]


def _fit(subject, head, config: FitConfig) -> dict:
    with tempfile.TemporaryDirectory(prefix="urhead-quality-") as out:
        result = Trainer(subject, head, config, Path(out), progress=False).run()
        rows = (Path(out) / "psnr_vs_time.csv").read_text().splitlines()[1:]
    m = result.metrics
    layout = MapLayout(config.sh_degree, config.gaussians)
    map_bytes = config.uv_resolution**2 * layout.channels * 4
    return {
        "psnr": m["psnr"],
        "ssim": m["ssim"],
        "psnr_mesh_only": m["psnr_mesh_only"],
        "num_gaussians": m["num_gaussians"],
        "seconds": m["seconds"],
        "ms_per_iteration": 1e3 * m["seconds"] / config.iterations,
        "maps_and_adam_mb": 3 * map_bytes / 2**20,
        "curve": [[float(x) for x in r.split(",")] for r in rows],
    }


def run(quick: bool) -> dict:
    with one_torch_thread():
        subject_dir = synthesize(ROOT / ".cache" / "quality_subject", SUBJECT, progress=False)
        subject = load_subject(subject_dir)
        head = procedural_head(0)
        iterations = 300 if quick else 800
        base = replace(
            FitConfig(),
            **{
                **FIT_PRESETS["quick"],
                "iterations": iterations,
                "lr_decay_start": iterations // 3,
                "sample_every": iterations // 6,
                "eval_every_seconds": 10.0 if quick else 20.0,
                "eval_frames": 8,
                "checkpoint_every": 10**9,
            },
        )
        results = {}
        for group, name, overrides in RUNS:
            print(f"   {name}", flush=True)
            results[name] = {"group": group, **_fit(subject, head, replace(base, **overrides))}
        return {"iterations": iterations, "subject_frames": SUBJECT.frames, "runs": results}


def render(results: dict, figures: Path) -> str:
    import matplotlib.pyplot as plt

    runs = results["runs"]
    base = runs[BASE]
    rows = []
    for name, r in runs.items():
        mesh = r["psnr_mesh_only"]
        rows.append(
            [
                name,
                f"{r['psnr']:.2f}",
                f"{r['ssim']:.4f}",
                f"{mesh:.2f}" if mesh is not None else "—",
                f"{r['num_gaussians']:,}",
                f"{r['seconds']:.0f}",
                f"{r['ms_per_iteration']:.0f}",
                f"{r['maps_and_adam_mb']:.0f}",
            ]
        )
    groups = sorted({r["group"] for r in runs.values()})
    fig, axes = plt.subplots(1, len(groups), figsize=(3.3 * len(groups), 3.2), sharey=True)
    for ax, group in zip(axes, groups, strict=True):
        for name, r in runs.items():
            if r["group"] == group or name == BASE:
                curve = r["curve"]
                style = "k--" if name == BASE and r["group"] != group else "-"
                ax.plot([c[0] for c in curve], [c[2] for c in curve], style, label=name)
        ax.set_title(group, fontsize=9)
        ax.set_xlabel("training seconds")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    axes[0].set_ylabel("held-out PSNR (dB)")
    saved = {
        name: (base["ms_per_iteration"] - r["ms_per_iteration"], r["maps_and_adam_mb"])
        for name, r in runs.items()
    }
    pays = [
        [
            "no normal maps (normal loss off)",
            f"{saved['no normal loss'][0]:+.0f} ms/iteration",
            "no rendered normals, no normal loss (here simulated by switching the loss off; "
            "the subject's normal images were still decoded)",
        ],
        [
            "SH degree 0 instead of 3",
            f"{saved['SH 0'][0]:+.0f} ms/iteration",
            f"maps + Adam state {base['maps_and_adam_mb']:.0f} → "
            f"{saved['SH 0'][1]:.0f} MB ({MapLayout(0).channels} instead of "
            f"{MapLayout(3).channels} channels at the same resolution)",
        ],
        [
            "mesh only (no Gaussians)",
            f"{saved['mesh only'][0]:+.0f} ms/iteration",
            f"no O, S maps: {saved['mesh only'][1]:.0f} MB; no lift, splat or sampling",
        ],
        [
            "closed mouth",
            "see below",
            "the scene analysis drops a closed mouth's interior and teeth: section "
            "'What leaving out pays'",
        ],
    ]
    return "\n\n".join(
        [
            f"The hard subject (`--difficulty hard`, the built-in subject before the capture "
            f"conditions; {results['subject_frames']} frames, 512², tracked FLAME with noise), "
            f"{results['iterations']} iterations of the quick preset's settings "
            "per run (shorter than the preset, so the comparison is at equal cost); held-out "
            "PSNR/SSIM over the whole test split, inside the mask. Positive 'saved' figures are "
            "time saved per iteration relative to the quick-preset row.",
            table(
                [
                    "run",
                    "PSNR",
                    "SSIM",
                    "mesh-only PSNR",
                    "Gaussians",
                    "train s",
                    "ms/it",
                    "maps+Adam MB",
                ],
                rows,
            ),
            save(fig, figures, "quality_vs_time"),
            "### Switches and what they save",
            table(["scene lacks / needs", "time saved", "also"], pays),
        ]
    )
