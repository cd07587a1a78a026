"""Configuration: frozen dataclasses, with the command line generated from their fields.

Every field becomes ``--field-name`` with the field's type and default; the field's
``metadata["help"]`` is its help text. Booleans take ``--flag`` / ``--no-flag``. Presets
are dicts of overrides applied before explicit command-line values.
"""

from __future__ import annotations

import argparse
import math
import typing
from dataclasses import dataclass, field, fields, replace
from typing import Literal

from urhead.data.background import parse_background
from urhead.errors import InvalidArgumentError


def option(default, help: str, **kwargs):
    """A dataclass field with help text for the generated command line."""
    return field(default=default, metadata={"help": help, **kwargs})


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_arguments(
    parser: argparse.ArgumentParser, cls: type, presets: dict[str, dict] | None = None
) -> None:
    """Adds one option per field of the dataclass ``cls``; defaults are left as None so
    presets can tell what the user set explicitly. The help names the field's default and
    each preset's value where a preset changes it."""
    hints = typing.get_type_hints(cls)
    for f in fields(cls):
        kind = hints[f.name]
        overrides = "".join(
            f"; --preset {name}: {values[f.name]}"
            for name, values in (presets or {}).items()
            if f.name in values
        )
        help_text = f"{f.metadata.get('help', '')} (default: {f.default}{overrides})"
        if kind is bool:
            parser.add_argument(
                _flag(f.name),
                dest=f.name,
                default=None,
                action=argparse.BooleanOptionalAction,
                help=help_text,
            )
        elif typing.get_origin(kind) is Literal:
            choices = typing.get_args(kind)
            parser.add_argument(
                _flag(f.name), dest=f.name, default=None, choices=choices, help=help_text
            )
        else:
            parser.add_argument(_flag(f.name), dest=f.name, default=None, type=kind, help=help_text)


def from_arguments(
    cls: type,
    args: argparse.Namespace,
    presets: dict[str, dict] | None = None,
    preset: str | None = None,
):
    """The config: field defaults, then the preset's overrides, then explicit options."""
    config = cls()
    if preset is not None:
        if not presets or preset not in presets:
            raise InvalidArgumentError(
                f"preset must be one of {sorted(presets or {})}, got {preset!r}"
            )
        config = replace(config, **presets[preset])
    explicit = {
        f.name: getattr(args, f.name)
        for f in fields(cls)
        if getattr(args, f.name, None) is not None
    }
    return replace(config, **explicit)


RESUMABLE_CHANGES = ("map_moments",)
"""FitConfig fields a resumed fit may set differently from its checkpoint: how state is
stored, not what is fitted (moments saved in either precision load into either)."""

KEEPABLE_PARTS = ("mouth", "eyes")
"""The model parts a fit leaves out when its scene analysis finds the scene lacks them
(:mod:`urhead.train.scene`), and ``--keep`` forces back."""


@dataclass(frozen=True)
class FitConfig:
    """Everything that shapes a fit. Defaults are the paper's (Sec. 4.1 and the supplement)
    where it states them; the rest are ours, marked as such."""

    iterations: int = option(50_000, "training iterations (paper: 50k)")
    uv_resolution: int = option(2048, "side of every UV map (paper: 2048)")
    sh_degree: int = option(3, "spherical-harmonics degree of the colour map, 0-3 (paper: 3)")
    sh_degree_every: int = option(
        0,
        "iterations between raising the SH degree used by one, from 0 up to sh_degree "
        "(0 = the full degree from the start, as the paper; 3DGS: 1000)",
    )
    sh_rest_rate: float = option(
        1.0,
        "learning-rate factor of the SH bands above DC, relative to lr_color "
        "(paper: 1; 3DGS: 1/20)",
    )
    gaussian_offset: bool = option(
        False,
        "give the Gaussians their own offset map E along the normal, x = P + (D + E)·n, so "
        "they can leave the surface (hair) without moving the mesh (ours; paper: off)",
    )
    lr_offset: float = option(5e-5, "learning rate of E, metres (ours)")
    lambda_offset: float = option(
        1.0,
        "weight of the mean squared Gaussian offset E, in units of (100 mm)⁻²: an offset has "
        "to pay for itself in image error (ours)",
    )
    initial_gaussians: int = option(
        10_000, "Gaussians sampled uniformly over the UV surface at the start (ours)"
    )
    color_init_frames: int = option(
        8, "training frames projected onto the surface to initialise C; 0 = grey (ours)"
    )
    max_gaussians: int = option(30_000, "Gaussian budget (paper: ~24k on INSTA bala)")
    sample_every: int = option(500, "iterations between adaptive-sampling rounds (ours)")
    sample_cap: int = option(2_000, "new Gaussians per sampling round, at most (ours)")
    sampling: Literal["adaptive", "uniform"] = option(
        "adaptive", "where new Gaussians go: error-driven or uniform (ablation)"
    )
    error_grid: int = option(
        256, "side of the UV grid the photometric error is accumulated on for sampling (ours)"
    )
    prune_opacity: float = option(0.01, "prune Gaussians below this opacity (paper: 0.01)")
    prune_screen_fraction: float = option(
        0.1, "prune Gaussians whose screen radius exceeds this fraction of the image side (ours)"
    )
    depth_eps: float = option(0.01, "occlusion threshold against mesh depth, metres (paper: 0.01)")
    lr_color: float = option(5e-4, "learning rate of C (paper)")
    lr_normal: float = option(1e-3, "learning rate of N (paper)")
    lr_scale: float = option(5e-3, "learning rate of S (paper)")
    lr_opacity: float = option(5e-2, "learning rate of O (paper)")
    lr_displacement: float = option(1e-5, "learning rate of D (paper)")
    lr_expression: float = option(1e-3, "learning rate of FLAME expression (paper)")
    lr_pose: float = option(1e-5, "learning rate of FLAME pose (paper)")
    lr_translation: float = option(1e-6, "learning rate of FLAME translation (paper)")
    lr_decay_start: int = option(
        10_000,
        "iteration after which UV learning rates decay "
        "(paper: 'after the initial iterations'; ours)",
    )
    lr_decay_final: float = option(
        0.1, "UV learning-rate factor reached at the last iteration, exponential (ours)"
    )
    lambda_ssim: float = option(0.2, "weight of 1 − SSIM (paper does not state; 3DGS's 0.2)")
    mesh_term: float = option(
        0.2,
        "weight of the mesh-only L1 inside L_photo (paper: 0.2; 0 = ablation 'no 0.2 mesh term')",
    )
    lambda_alpha: float = option(
        0.0,
        "weight of the silhouette term: mean |coverage − mask| over the image, coverage the "
        "composite's opacity (ours; paper: none)",
    )
    lambda_normal: float = option(
        0.1, "weight of the normal loss when the subject has normals (paper does not state; ours)"
    )
    lambda_laplacian: float = option(
        1000.0,
        "weight of the Laplacian of the vertex displacements, metres (paper does not state; "
        "ours: a 1 mm bump on one vertex should cost about what a few pixels of error do)",
    )
    gaussians: bool = option(True, "use the Gaussian branch (off = ablation 'mesh only')")
    normal_loss: bool = option(True, "use the normal loss when normals exist (ablation)")
    occlusion_aware: bool = option(True, "skip Gaussian samples behind the mesh (ablation)")
    eval_every_seconds: float = option(
        60.0, "held-out PSNR logged at this wall-clock interval (ours)"
    )
    eval_frames: int = option(
        16, "held-out frames (evenly spread) scored for the PSNR-vs-time log (ours)"
    )
    shading: bool = option(
        False,
        "pose-driven shading maps A: colour × (1 + Σ A_ij (R − I)_ij), R the surface's "
        "rotation — light fixed in the room while the head turns (ours; paper: off)",
    )
    lr_shading: float = option(1e-3, "learning rate of the shading maps A (ours)")
    map_moments: Literal["float32", "bfloat16"] = option(
        "bfloat16",
        "storage of the maps' Adam moments: bfloat16 halves their memory and a third of "
        "the optimiser's memory traffic; the second moment is rounded stochastically so it "
        "still decays (ours)",
    )
    checkpoint_every: int = option(1_000, "iterations between atomic checkpoints (ours)")
    refine_steps: int = option(
        20,
        "test-time refinement: Adam steps on each held-out frame's FLAME row against the "
        "frozen avatar at ≤ 256 px, reported as psnr_refined beside psnr (ours)",
    )
    refine_full_steps: int = option(
        10,
        "test-time refinement steps at the frame's full size after refine_steps (the last "
        "fraction of a pixel of alignment; both 0 = no refinement; ours)",
    )
    keep: str = option(
        "",
        "parts of the model kept even where the scene analysis finds the training frames "
        "lack them, comma-separated: mouth (interior and teeth faces and texels), eyes "
        "(per-frame eye joints), or all (ours)",
    )
    seed: int = option(0, "random seed")
    background: str = option(
        "auto",
        "colour the subject's images are composited on: white, black or R,G,B (0-255); "
        "auto = detected from the pixels outside the masks. A colour the data contradicts "
        "is an error",
    )

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise InvalidArgumentError(f"{f.name} must be a finite number, got {value!r}")
        checks = [
            ("iterations", self.iterations >= 1),
            ("uv_resolution", 16 <= self.uv_resolution <= 8192),
            ("sh_degree", 0 <= self.sh_degree <= 3),
            ("max_gaussians", self.max_gaussians >= self.initial_gaussians >= 0),
            ("sample_every", self.sample_every >= 1),
            ("sample_cap", self.sample_cap >= 0),
            ("color_init_frames", self.color_init_frames >= 0),
            ("error_grid", self.error_grid >= 1),
            ("eval_frames", self.eval_frames >= 1),
            ("checkpoint_every", self.checkpoint_every >= 1),
            ("sh_degree_every", self.sh_degree_every >= 0),
            ("refine_steps", self.refine_steps >= 0),
            ("refine_full_steps", self.refine_full_steps >= 0),
            ("prune_opacity", 0 <= self.prune_opacity < 1),
            ("prune_screen_fraction", self.prune_screen_fraction > 0),
            ("eval_every_seconds", self.eval_every_seconds >= 0),
            ("depth_eps", self.depth_eps >= 0),
            ("lr_decay_final", 0 < self.lr_decay_final <= 1),
            ("mesh_term", 0 <= self.mesh_term <= 1),
            ("lambda_ssim", 0 <= self.lambda_ssim <= 1),
        ]
        for name, ok in checks:
            if not ok:
                raise InvalidArgumentError(f"{name} is out of range: {getattr(self, name)!r}")
        for name in (n.strip() for n in self.keep.split(",")):
            if name and name not in (*KEEPABLE_PARTS, "all"):
                raise InvalidArgumentError(
                    f"keep: {name!r} is not a part; choose from {', '.join(KEEPABLE_PARTS)} or all"
                )
        if self.background != "auto":
            parse_background(self.background)
        rates = [
            f.name
            for f in fields(self)
            if f.name.startswith(("lr_", "lambda_")) or f.name == "sh_rest_rate"
        ]
        for name in rates:
            value = getattr(self, name)
            if not (value >= 0 and value != float("inf")):
                raise InvalidArgumentError(f"{name} must be finite and >= 0, got {value!r}")


FIT_PRESETS: dict[str, dict] = {
    # The paper's schedule and resolution.
    "paper": {},
    # The built-in subject end to end in minutes on 2 cores: smaller maps, fewer iterations.
    "quick": {
        # Held-out PSNR is flat from ~900 iterations on (the main job at 512²: 25.9-26.1 dB
        # from 900 to 2000; 26.1-26.6 on 16 frames from 1100 to 1800); 1500 keep the main
        # job inside 15 minutes on 2 cores with the full-size refinement steps.
        "iterations": 1_500,
        "uv_resolution": 512,
        "initial_gaussians": 6_000,
        "max_gaussians": 15_000,
        "sample_every": 300,
        "sample_cap": 1_500,
        "lr_decay_start": 700,
        # Each texel is updated ~17x less often than in the paper's schedule: larger
        # colour steps (ours).
        "lr_color": 2.5e-3,
        # S and N likewise (main job, all 90 held-out frames, tracked / refined in the mask:
        # S ×5 +0.18 / +0.05 dB, S ×10 +0.00 / -0.08, S ×5 with N ×5 +0.19 / +0.14).
        "lr_scale": 2.5e-2,
        "lr_normal": 5e-3,
        # A frame's row is visited ~14 times: pose and translation 10x the paper's rates
        # (measured on the default subject at 256², held-out in-mask PSNR with tracked /
        # exact FLAME: +0.1 / +0.5 dB; 100x, with expression 1e-2, lost 1.0 / 0.8 dB).
        "lr_pose": 1e-4,
        "lr_translation": 2e-5,
        # Gaussians leave the surface where the hair is: +0.7 dB in the mask, +0.8 full
        # image on the default subject (D itself at 1e-4 tore the mesh apart: kept at 1e-5).
        # E at 4x the first rate and unregularised (the photometric and silhouette terms
        # bound it): tracked / refined in the mask +0.07 / +0.19 dB on the default subject
        # at 256², +0.20 / +0.32 on the hard one (strands); 5e-4 scored 0.10 / 0.06 below 5e-5.
        "gaussian_offset": True,
        "lr_offset": 2e-4,
        "lambda_offset": 0.0,
        # The silhouette fitted directly (default subject at 256², with the walking
        # antialias: +0.13 dB tracked / +0.22 refined in the mask; 2.0 without the walk:
        # +0.39 / +0.68 against +0.30 / +0.46 for 0.5).
        "lambda_alpha": 0.5,
        # Refinement coarse to fine, warm-started. The in-mask gain is made at full size
        # (15 steps at 256² alone: +0.28 dB in the mask, +2.2 on the full image, mostly the
        # silhouette), so a short coarse stage and more full-size steps: chosen on 24
        # consecutive training frames of the main job started from their tracked rows
        # (in-mask PSNR, wall s): 15 + 8 31.43 dB 63.6 s; 6 + 10 31.67, 53.3; 3 + 10 31.67,
        # 47.6; 0 + 12 31.55, 51.3; 15 + 12 31.71, 81.4; 6 + 12 31.71, 67.8.
        "refine_steps": 3,
        "refine_full_steps": 10,
        "eval_every_seconds": 30.0,
        "checkpoint_every": 500,
    },
}
