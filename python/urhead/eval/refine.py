"""Test-time refinement: a held-out frame's FLAME row fitted to its image against the frozen
avatar (FORMATS.md "Evaluation protocol": reported beside the tracked-parameter score,
labelled).

Why: a held-out frame arrives with the tracker's parameters, and the tracker's error
(a few pixels of face displacement) costs more than anything the avatar gets wrong. The
training frames' rows are refined during the fit; this does the same for a held-out frame
with the avatar fixed — the maps and Gaussians never change, so the score still measures
the avatar, not a per-frame fit of it.

The objective is the fit's photometric one (0.8 L1 + 0.2 (1 − SSIM) over the matted image),
minimised by Adam on the expression, pose and translation with per-group rates. Frames in
timestep order start from the previous frame's correction (tracker error drifts slowly),
so fewer steps reach the same score.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from urhead.losses import l1, ssim_l1
from urhead.model.avatar import Avatar, FlameParams


@dataclass(frozen=True)
class RefineSettings:
    """How a held-out frame's FLAME row is refined."""

    steps: int = 20
    """Adam steps per frame at the reduced size (``max_side``)."""
    lr_expression: float = 1e-2
    lr_pose: float = 1e-3
    """radians per step, about."""
    lr_translation: float = 2e-4
    """metres per step, about."""
    lambda_ssim: float = 0.2
    warm_start: bool = True
    """Start a frame from the previous (consecutive) frame's correction."""
    max_side: int = 256
    """Refine on the frame resampled (area average) so its longer side is at most this:
    the coarse pose is found as well at 256² as at 512², in a quarter of the time."""
    coarse_max_steps: int = 0
    """The reduced-size stage goes on past ``steps``, up to this many, while its last step
    still lowered the loss by ``coarse_min_gain`` or more: ~1 px of tracker error is found
    in ~3 steps, ~4 px needs more. Off by default (0): on the main job's validation split
    (3 + 10 steps, up to 15) it scored 29.03 dB either way for 1.6× the refinement time; on
    24 training frames of the hard subject, started from their tracked rows, 24.29 → 25.10
    (`urhead eval --refine-coarse-max-steps 15`)."""
    coarse_min_gain: float = 0.03
    """Relative loss decrease of a step below which the extended stage stops (a 1 %
    threshold: 28.99 / 25.15 on the frames above)."""
    full_steps: int = 10
    """Adam steps at the frame's own size after the coarse ones: the last fraction of a
    pixel of alignment only shows at full resolution."""

    @property
    def total_steps(self) -> int:
        """Steps per frame over both sizes (0 = no refinement)."""
        return self.steps + self.full_steps

    def __post_init__(self):
        for name in ("steps", "full_steps", "coarse_max_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"refine {name} must be >= 0, got {getattr(self, name)}")
        if self.max_side < 16:
            raise ValueError(f"refine max_side must be >= 16, got {self.max_side}")
        for name in (
            "lr_expression",
            "lr_pose",
            "lr_translation",
            "lambda_ssim",
            "coarse_min_gain",
        ):
            value = getattr(self, name)
            if not (0 <= value < float("inf")):
                raise ValueError(f"refine {name} must be finite and >= 0, got {value!r}")


def refine_params(
    avatar: Avatar,
    frame,
    start: FlameParams,
    settings: RefineSettings,
    *,
    occlusion_aware: bool = True,
) -> FlameParams:
    """``start`` refined against ``frame`` (image, mask, camera) with the avatar frozen:
    ``settings.steps`` at the reduced size, then ``settings.full_steps`` at full size.
    Returns detached parameters; the avatar's tensors are not modified."""
    if avatar.maps.requires_grad:
        # A backward through the maps would build a dense gradient and leave it in
        # maps.grad; refinement is for a frozen avatar.
        raise ValueError("refine_params needs a frozen avatar (maps.requires_grad is set)")
    coarse = _adam_descent(
        avatar,
        *_resampled(frame, settings.max_side),
        start,
        settings.steps,
        settings,
        occlusion_aware,
        max_steps=settings.coarse_max_steps,
    )
    full_size = max(frame.image.shape[:2]) <= settings.max_side
    if full_size:
        return coarse
    return _adam_descent(
        avatar, frame.camera, frame.image, coarse, settings.full_steps, settings, occlusion_aware
    )


def _adam_descent(avatar, camera, target, start, steps, settings, occlusion_aware, max_steps=0):
    """``start`` after ``steps`` Adam steps on the photometric objective at ``camera`` — and
    after more, up to ``max_steps``, while a step still lowers the loss by
    ``settings.coarse_min_gain``; the best scored state (never worse than ``start``)."""
    if steps == 0:
        return start
    expr, pose, transl = (p.detach().clone().requires_grad_(True) for p in start)
    optimizer = torch.optim.Adam(
        [
            {"params": [expr], "lr": settings.lr_expression},
            {"params": [pose], "lr": settings.lr_pose},
            {"params": [transl], "lr": settings.lr_translation},
        ]
    )
    w = settings.lambda_ssim
    best, best_loss = start, float("inf")
    losses = []
    for step in range(max(steps, max_steps)):
        if step >= steps and not _still_falling(losses, settings.coarse_min_gain):
            break
        optimizer.zero_grad(set_to_none=True)
        params = FlameParams(expr, pose, transl)
        image = avatar.render(params, camera, occlusion_aware=occlusion_aware).image
        # (1 − λ)·L1 + λ·(1 − SSIM), the weights inside one kernel pass (as the fit's objective)
        if w > 0:
            loss = ssim_l1(image, target, ssim_weight=-w, l1_weight=1 - w) + w
        else:
            loss = l1(image, target)
        value = float(loss.detach())
        losses.append(value)
        if value < best_loss and torch.isfinite(loss):
            best = FlameParams(*(p.detach().clone() for p in params))
            best_loss = value
        loss.backward()
        optimizer.step()
    # The last step's result is not scored; the best scored state is kept, so refinement
    # can never end worse than where it started.
    return best


def _still_falling(losses: list[float], min_gain: float) -> bool:
    """Whether the last scored loss is below the one before by ``min_gain`` (relative)."""
    return len(losses) >= 2 and losses[-1] <= losses[-2] * (1 - min_gain)


def _resampled(frame, max_side: int):
    """``(camera, image)`` of ``frame`` with its longer side at most ``max_side``."""
    h, w = frame.image.shape[:2]
    factor = max_side / max(h, w)
    if factor >= 1:
        return frame.camera, frame.image
    size = (max(1, round(h * factor)), max(1, round(w * factor)))
    image = F.interpolate(frame.image.permute(2, 0, 1)[None], size=size, mode="area")
    return frame.camera.resized(size[1], size[0]), image[0].permute(1, 2, 0).contiguous()


def refine_sequence(
    avatar: Avatar,
    frames: Sequence,
    starts: Sequence[FlameParams],
    settings: RefineSettings,
    *,
    occlusion_aware: bool = True,
    progress=None,
) -> list[FlameParams]:
    """Refines each of ``frames`` from its ``starts`` entry; with ``warm_start``, a frame
    that follows its predecessor (same camera, next timestep) starts from its tracked
    parameters plus the predecessor's correction. ``progress`` is called once per frame."""
    refined: list[FlameParams] = []
    correction = None
    previous = None
    for frame, start in zip(frames, starts, strict=True):
        follows = (
            previous is not None
            and frame.timestep == previous.timestep + 1
            and frame.camera_index == previous.camera_index
        )
        begin = start
        if settings.warm_start and follows and correction is not None:
            begin = FlameParams(*(s + c for s, c in zip(start, correction, strict=True)))
        out = refine_params(avatar, frame, begin, settings, occlusion_aware=occlusion_aware)
        correction = FlameParams(*(o - s for o, s in zip(out, start, strict=True)))
        refined.append(out)
        previous = frame
        if progress is not None:
            progress()
    return refined
