"""Image metrics of an avatar over a sequence of frames, inside the head mask, on the
subject's background: PSNR and SSIM of the composite and PSNR of the mesh branch alone.
LPIPS needs network weights that cannot be downloaded here; it is reported as None unless
a caller supplies a scorer."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from urhead.losses import psnr, ssim
from urhead.model.avatar import Avatar, FlameParams


@dataclass(frozen=True)
class FrameScores:
    """Means over the frames; ``per_frame_psnr`` keeps each frame's value."""

    psnr: float
    ssim: float
    psnr_mesh_only: float | None
    lpips: float | None
    per_frame_psnr: tuple[float, ...]


def frame_params(avatar: Avatar, frame) -> FlameParams:
    """The avatar's trained parameters for a training timestep, else the frame's tracked
    ones (held-out frames)."""
    if bool((avatar.timesteps == frame.timestep).any()):
        return avatar.frame(frame.timestep)
    return avatar.params_from_flame(frame.flame)


@torch.no_grad()
def evaluate_frames(
    avatar: Avatar,
    frames: Sequence,
    *,
    occlusion_aware: bool = True,
    mesh_only: bool = True,
    lpips: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], float] | None = None,
) -> FrameScores:
    """Scores ``frames`` (dataset frames with image, mask, camera, flame)."""
    if len(frames) == 0:
        raise ValueError("frames is empty: nothing to evaluate")
    psnrs, ssims, mesh_psnrs, lpipss = [], [], [], []
    for frame in frames:
        params = frame_params(avatar, frame)
        out = avatar.render(params, frame.camera, occlusion_aware=occlusion_aware)
        image = out.image.clamp(0, 1)
        psnrs.append(float(psnr(image, frame.image, frame.mask)))
        ssims.append(float(ssim(image, frame.image, frame.mask)))
        if mesh_only:
            mesh = out.mesh.image.clamp(0, 1)
            mesh_psnrs.append(float(psnr(mesh, frame.image, frame.mask)))
        if lpips is not None:
            lpipss.append(float(lpips(image, frame.image, frame.mask)))
    mean = lambda xs: sum(xs) / len(xs) if xs else None  # noqa: E731
    return FrameScores(mean(psnrs), mean(ssims), mean(mesh_psnrs), mean(lpipss), tuple(psnrs))
