"""The one per-frame evaluation loop (FORMATS.md "Evaluation protocol"), behind the fit's
``metrics.json``, ``urhead eval`` and the main job's oracle scores.

Each frame is rendered with its FLAME parameters on the avatar's background and scored
against its ground truth: PSNR inside the head mask and over the whole image, SSIM inside
the mask, the render's wall time; on request the mesh branch's PSNR, perceptual distances
inside the mask (named scorers such as LPIPS, and ST-LPIPS) and temporal stability.

Temporal stability, over consecutive frame pairs (same camera, timesteps t−1 and t):
- ``temporal_error_change``: the masked mean of |(Î_t − I_t) − (Î_{t−1} − I_{t−1})| inside
  both frames' masks;
- ``temporal_<scorer>``: |d(Î_t, Î_{t−1}) − d(I_t, I_{t−1})| for each perceptual scorer d
  (ST-LPIPS as ``temporal_stlpips_alex``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch

from urhead._progress import tracked
from urhead.losses import masked_mean, psnr, ssim

Scorer = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], float]
"""A perceptual distance of (image, target, mask): (H, W, 3), (H, W, 3), (H, W)."""

METRIC_REGION = (
    "psnr, ssim: inside each frame's foreground mask; *_full: the whole image; on the "
    "avatar's background"
)
FLAME_PARAMETERS = (
    "psnr*: held-out frames with their tracked FLAME parameters; *_refined: after "
    "refine_steps Adam steps at <= 256 px, then refine_full_steps at full size, on each "
    "held-out frame's FLAME row against the frozen avatar"
)
"""The two reports' (metrics.json, ``urhead eval``) description of what they score."""


@dataclass
class PerFrameScores:
    """Each frame's scores, in frame order; ``temporal`` holds one value per consecutive
    pair under each temporal key (module docstring)."""

    timesteps: list[int] = field(default_factory=list)
    psnr: list[float] = field(default_factory=list)
    psnr_full: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    psnr_mesh_only: list[float] = field(default_factory=list)
    perceptual: dict[str, list[float]] = field(default_factory=dict)
    stlpips_alex: list[float] = field(default_factory=list)
    temporal: dict[str, list[float]] = field(default_factory=dict)


@torch.no_grad()
def score_frames(
    avatar,
    frames: Sequence,
    params: Sequence,
    *,
    occlusion_aware: bool = True,
    mesh_only: bool = False,
    perceptual: Mapping[str, Scorer] | None = None,
    stlpips=None,
    temporal: bool = False,
    progress: bool = False,
) -> PerFrameScores:
    """Renders each of ``frames`` (dataset frames with image, mask, camera) with its entry
    of ``params`` and scores it. ``mesh_only`` adds the mesh branch's in-mask PSNR;
    ``perceptual`` maps names to scorers; ``stlpips`` is a
    :class:`~urhead.eval.stlpips.StLpips` (its features are reused for the temporal term);
    ``temporal`` adds the pair scores; ``progress`` shows a bar."""
    perceptual = dict(perceptual or {})
    scores = PerFrameScores(perceptual={name: [] for name in perceptual})
    if temporal:
        keys = ["error_change", *perceptual] + (["stlpips_alex"] if stlpips is not None else [])
        scores.temporal = {f"temporal_{key}": [] for key in keys}
    features = None  # ST-LPIPS features of this frame's (render, ground truth)
    previous = None
    for frame, p in zip(
        tracked(frames, len(frames), "eval", enabled=progress), params, strict=True
    ):
        start = time.perf_counter()
        out = avatar.render(p, frame.camera, occlusion_aware=occlusion_aware)
        scores.seconds.append(time.perf_counter() - start)
        image = out.image.clamp(0, 1)
        scores.timesteps.append(frame.timestep)
        scores.psnr.append(float(psnr(image, frame.image, frame.mask)))
        scores.psnr_full.append(float(psnr(image, frame.image)))
        scores.ssim.append(float(ssim(image, frame.image, frame.mask)))
        if mesh_only:
            mesh = out.mesh.image.clamp(0, 1)
            scores.psnr_mesh_only.append(float(psnr(mesh, frame.image, frame.mask)))
        for name, scorer in perceptual.items():
            scores.perceptual[name].append(float(scorer(image, frame.image, frame.mask)))
        previous_features = features
        if stlpips is not None:
            features = (stlpips.features(image), stlpips.features(frame.image))
            scores.stlpips_alex.append(stlpips.distance(*features, frame.mask))
        if temporal and previous is not None and _consecutive(previous[0], frame):
            prev_frame, prev_image = previous
            mask = frame.mask * prev_frame.mask
            change = (image - frame.image) - (prev_image - prev_frame.image)
            scores.temporal["temporal_error_change"].append(float(masked_mean(change.abs(), mask)))
            for name, scorer in perceptual.items():
                ours = scorer(image, prev_image, mask)
                truth = scorer(frame.image, prev_frame.image, mask)
                scores.temporal[f"temporal_{name}"].append(abs(ours - truth))
            if stlpips is not None:
                ours = stlpips.distance(features[0], previous_features[0], mask)
                truth = stlpips.distance(features[1], previous_features[1], mask)
                scores.temporal["temporal_stlpips_alex"].append(abs(ours - truth))
        previous = (frame, image)
    return scores


def mean(values: Sequence[float]) -> float | None:
    """The mean of ``values`` (exactly rounded sum), None for none."""
    return math.fsum(values) / len(values) if values else None


def variance(values: Sequence[float]) -> float | None:
    """The population variance of ``values``, None for none."""
    if not values:
        return None
    m = mean(values)
    return math.fsum((x - m) ** 2 for x in values) / len(values)


def _consecutive(a, b) -> bool:
    return b.timestep == a.timestep + 1 and b.camera_index == a.camera_index
