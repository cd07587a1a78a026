"""Image metrics of an avatar over a sequence of frames (FORMATS.md "Evaluation protocol"):
the means of the per-frame loop (:mod:`urhead.eval.per_frame`) — PSNR inside the head mask
(``psnr``) and over the full image (``psnr_full``), SSIM inside the mask, PSNR of the mesh
branch alone; the same PSNRs after test-time refinement of the held-out frames' FLAME rows
(``psnr_refined``, ``psnr_refined_full``) when asked for. LPIPS needs network weights that
cannot be downloaded here; it is None unless a caller supplies a scorer. ST-LPIPS-alex
(``stlpips_alex``, :mod:`urhead.eval.stlpips`) likewise, inside the mask."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import torch

from urhead.eval.per_frame import mean, score_frames
from urhead.eval.refine import RefineSettings, refine_sequence
from urhead.model.avatar import Avatar, FlameParams


@dataclass(frozen=True)
class FrameScores:
    """Means over the frames; ``per_frame_psnr`` keeps each frame's in-mask value."""

    psnr: float
    psnr_full: float
    ssim: float
    psnr_mesh_only: float | None
    lpips: float | None
    per_frame_psnr: tuple[float, ...]
    psnr_refined: float | None = None
    psnr_refined_full: float | None = None
    ssim_refined: float | None = None
    stlpips_alex: float | None = None
    refined_params: tuple[FlameParams, ...] | None = None
    """Each frame's parameters after refinement (with ``refine``), in ``frames`` order."""


def frame_params(avatar: Avatar, frame) -> FlameParams:
    """The avatar's trained parameters for a training timestep, else the frame's tracked
    ones (held-out frames)."""
    if bool((avatar.timesteps == frame.timestep).any()):
        return avatar.frame(frame.timestep)
    return avatar.params_from_flame(frame.flame)


def evaluate_frames(
    avatar: Avatar,
    frames: Sequence,
    *,
    occlusion_aware: bool = True,
    mesh_only: bool = True,
    lpips: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], float] | None = None,
    stlpips: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], float] | None = None,
    refine: RefineSettings | None = None,
    progress=None,
    params: Sequence[FlameParams] | None = None,
) -> FrameScores:
    """Scores ``frames`` (dataset frames with image, mask, camera, flame) with ``params``
    (default: :func:`frame_params` of each); ``lpips`` and ``stlpips`` score (image, truth,
    mask) when given; with ``refine`` (steps > 0) also after refining
    each held-out frame's FLAME row (training frames keep their trained rows).
    ``progress`` is called once per refined frame."""
    if len(frames) == 0:
        raise ValueError("frames is empty: nothing to evaluate")
    frames = list(frames)
    if params is None:
        params = [frame_params(avatar, f) for f in frames]
    elif len(params) != len(frames):
        raise ValueError(f"{len(params)} parameter sets for {len(frames)} frames")
    per = score_frames(
        avatar,
        frames,
        params,
        occlusion_aware=occlusion_aware,
        mesh_only=mesh_only,
        perceptual={} if lpips is None else {"lpips": lpips},
        stlpips=stlpips,
    )
    scores = FrameScores(
        psnr=mean(per.psnr),
        psnr_full=mean(per.psnr_full),
        ssim=mean(per.ssim),
        psnr_mesh_only=mean(per.psnr_mesh_only),
        lpips=mean(per.perceptual.get("lpips", [])),
        per_frame_psnr=tuple(per.psnr),
        stlpips_alex=mean(per.stlpips_alex),
    )
    if refine is None or refine.total_steps == 0:
        return scores
    refined = refine_params_of(avatar, frames, refine, occlusion_aware, progress, params)
    after = score_frames(avatar, frames, refined, occlusion_aware=occlusion_aware)
    return replace(
        scores,
        psnr_refined=mean(after.psnr),
        psnr_refined_full=mean(after.psnr_full),
        ssim_refined=mean(after.ssim),
        refined_params=tuple(refined),
    )


def refine_params_of(
    avatar: Avatar,
    frames: Sequence,
    settings: RefineSettings,
    occlusion_aware=True,
    progress=None,
    starts: Sequence[FlameParams] | None = None,
) -> list[FlameParams]:
    """Each frame's parameters after test-time refinement from ``starts`` (default:
    :func:`frame_params`); training frames (whose rows the fit already refined) keep
    theirs."""
    held = [i for i, f in enumerate(frames) if not bool((avatar.timesteps == f.timestep).any())]
    params = list(starts) if starts is not None else [frame_params(avatar, f) for f in frames]
    held_frames = [frames[i] for i in held]
    refined = refine_sequence(
        avatar,
        held_frames,
        [params[i] for i in held],
        settings,
        occlusion_aware=occlusion_aware,
        progress=progress,
    )
    for i, p in zip(held, refined, strict=True):
        params[i] = p
    return params


def exact_flame_scores(avatar: Avatar, frames: Sequence, truth_path) -> FrameScores:
    """Scores of ``frames`` driven by a synthetic subject's exact FLAME parameters
    (``synthetic_ground_truth.npz``: expr (T, E), pose (T, 15), transl (T, 3)) instead of
    the tracked ones: the oracle for tracking error, which only a synthetic subject has."""
    import numpy as np

    frames = list(frames)
    e = avatar.num_expr
    with np.load(truth_path) as truth:
        exact = [
            FlameParams(
                torch.from_numpy(truth["expr"][f.timestep, :e].copy()),
                torch.from_numpy(truth["pose"][f.timestep].copy()),
                torch.from_numpy(truth["transl"][f.timestep].copy()),
            )
            for f in frames
        ]
    return evaluate_frames(avatar, frames, params=exact, mesh_only=False)
