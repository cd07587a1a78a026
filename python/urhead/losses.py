"""Image metrics and losses of the paper (Sec. "Training Objectives"), masked: every term is
averaged inside the head mask, so background pixels neither train nor score.

Images are (H, W, C) float tensors in [0, 1]; masks are (H, W) in [0, 1] or bool.
:func:`ssim`, :func:`l1`, :func:`ssim_l1` and :func:`pixel_l1` run the fused Rust kernels of
:mod:`urhead.ops.ssim` for CPU float32/float64 images with a constant target and mask (the
training loop's case) and fall back to the plain-torch references of
:mod:`urhead.ops._reference` otherwise.
"""

from __future__ import annotations

import torch

from urhead.ops import _reference as reference
from urhead.ops._reference import masked_mean, ssim_map
from urhead.ops.ssim import masked_l1, masked_pixel_l1, masked_ssim, masked_ssim_l1


def _kernel_applies(image, target, mask) -> bool:
    """Whether the Rust kernels take these inputs: CPU (H, W, C) float32/float64 of one dtype,
    differentiated in ``image`` only."""
    tensors = [image, target] + ([] if mask is None else [mask])
    return (
        all(isinstance(t, torch.Tensor) and t.device.type == "cpu" for t in tensors)
        and image.dtype in (torch.float32, torch.float64)
        and target.dtype == image.dtype
        and image.dim() == 3
        and not target.requires_grad
        and not (mask is not None and mask.requires_grad)
    )


def ssim(image, target, mask=None, *, weight: float = 1.0) -> torch.Tensor:
    """Mean SSIM inside ``mask``, times ``weight`` (a loss term's: the kernel scales its
    gradient as it computes it)."""
    if _kernel_applies(image, target, mask):
        mask = None if mask is None else mask.contiguous()
        return masked_ssim(image.contiguous(), target.contiguous(), mask, weight=weight)
    return weight * masked_mean(ssim_map(image, target), mask)


def l1(image, target, mask=None, *, weight: float = 1.0) -> torch.Tensor:
    """Mean absolute error inside ``mask``, times ``weight``; ``image`` may hold more
    channels than ``target``, its first C compared (an RGBA image against an RGB target)."""
    if _kernel_applies(image, target, mask):
        mask = None if mask is None else mask.contiguous()
        return masked_l1(image.contiguous(), target.contiguous(), mask, weight=weight)
    return weight * masked_mean((image[..., : target.shape[-1]] - target).abs(), mask)


def ssim_l1(image, target, mask=None, *, ssim_weight: float, l1_weight: float) -> torch.Tensor:
    """``ssim_weight · ssim(...) + l1_weight · l1(...)`` of the same images: one kernel pass
    and one gradient where the kernels apply (:func:`~urhead.ops.masked_ssim_l1`), the two
    references otherwise."""
    if _kernel_applies(image, target, mask) and image.shape == target.shape:
        mask = None if mask is None else mask.contiguous()
        return masked_ssim_l1(
            image.contiguous(),
            target.contiguous(),
            mask,
            ssim_weight=ssim_weight,
            l1_weight=l1_weight,
        )
    return ssim(image, target, mask, weight=ssim_weight) + l1(image, target, mask, weight=l1_weight)


def pixel_l1(values, pixels, target, mask, *, weight: float = 1.0) -> torch.Tensor:
    """Mean ‖v_p − target[x_p]‖₁ of ``values (P, C)`` at their ``pixels`` over the mask
    where the target holds data, times ``weight`` (the normal loss): the kernel of
    :func:`~urhead.ops.masked_pixel_l1` for float32/float64 values of the target's dtype,
    the plain-torch reference otherwise."""
    if values.dtype in (torch.float32, torch.float64) and target.dtype == values.dtype:
        return masked_pixel_l1(values, pixels, target, mask, weight=weight)
    return weight * reference.masked_pixel_l1(values, pixels, target, mask)


def psnr(image, target, mask=None) -> torch.Tensor:
    """PSNR in dB of [0, 1] images, from the MSE inside ``mask``."""
    mse = masked_mean((image - target) ** 2, mask)
    return -10 * torch.log10(mse.clamp_min(1e-20))
