"""A small avatar for the ``urhead eval/render/reenact/export`` tests: a 64² synthetic
subject and an untrained 64² avatar whose maps are randomised (so every SH band, opacity
and scale carries signal), saved with its subject (absolute and relative paths) and camera
like a fit's."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from urhead.data import load_subject
from urhead.data.synth.subject import SynthConfig, synthesize
from urhead.head import procedural_head
from urhead.model import build_avatar, save_avatar
from urhead.model.avatar import POSE_SIZE
from urhead.use.common import subject_record

TINY = SynthConfig(
    frames=10, resolution=64, seed=5, difficulty="easy", samples_per_side=1, edge_samples_per_side=1
)
RIGID_TIMESTEP = 1
"""A frame whose pose is a global rotation only: every vertex then has the same skinning
rotation, a proper rotation, so the world-frame SH of the PLY export is exact."""
JAW_TIMESTEP = 2
"""A frame with a wide-open jaw and turned neck: skinning blends differing rotations."""


@dataclass
class UseAvatar:
    subject_dir: Path
    avatar_dir: Path


def make_use_avatar(root: Path) -> UseAvatar:
    subject_dir = synthesize(root / "subject", TINY, progress=False)
    subject = load_subject(subject_dir)
    avatar = build_avatar(
        procedural_head(0),
        subject.train,
        resolution=64,
        sh_degree=3,
        gaussians=True,
        initial_gaussians=300,
        background=torch.ones(3),
        depth_eps=0.01,
        color_frames=2,
        rng=np.random.default_rng(0),
    )
    g = torch.Generator().manual_seed(3)
    layout = avatar.layout
    with torch.no_grad():
        maps = avatar.maps
        maps[..., 3 : 3 * layout.sh_coeffs] = 0.3 * torch.randn(
            64, 64, 3 * layout.sh_coeffs - 3, generator=g
        )
        maps[..., layout.opacity] += torch.randn(64, 64, generator=g)
        maps[..., layout.scale] += 0.3 * torch.randn(64, 64, 3, generator=g)
        e = avatar.num_expr
        rows = avatar.frame_params
        rigid = avatar.frame_row(RIGID_TIMESTEP)
        rows[rigid, e : e + POSE_SIZE] = 0
        rows[rigid, e : e + 3] = torch.tensor([0.2, -0.5, 0.15])
        jaw = avatar.frame_row(JAW_TIMESTEP)
        rows[jaw, e + 3 : e + 9] = torch.tensor([0.1, 0.3, 0.0, 0.35, 0.0, 0.0])
    avatar_dir = save_avatar(
        avatar,
        root / "avatar",
        extra={
            **subject_record(root / "avatar", subject_dir),
            "camera": subject.train.records[0].camera.to_dict(),
        },
    )
    return UseAvatar(subject_dir, avatar_dir)
