"""Mean SSIM (a similarity) and mean L1 (a loss) of two images inside a mask, with Rust
kernels (the training loop's loss stage), apart or weighted together in one pass.

Both kernels compute the value and, when ``image`` requires grad, its gradient in the same
call (the SSIM gradient reuses the forward's blurred moments while they are in cache). A
loss term's ``weight`` is folded into the kernel's per-pixel scale, so a loss built as a sum
of weighted terms gets its gradient back as computed: the backward scales it only when the
incoming gradient is not exactly 1 (saving a pass over the image per term a step).
``target`` and ``mask`` are constants.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from urhead._threads import num_threads
from urhead.errors import InvalidArgumentError
from urhead.ops._bridge import check_tensor, float_dtype, native, to_numpy

_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


class _MaskedImageComparison(torch.autograd.Function):
    """``Σ_k weights[k] · metric_k(image, target)`` for ``metric`` "ssim", "l1" or
    "ssim+l1" (both from one kernel pass, one gradient)."""

    @staticmethod
    def forward(ctx, metric, image, target, mask, weights):
        dtype = image.dtype
        args = (
            to_numpy("image", image, dtype),
            to_numpy("target", target, dtype),
            None if mask is None else to_numpy("mask", mask, dtype),
        )
        ctx.set_materialize_grads(False)
        if not ctx.needs_input_grad[1]:
            values = [native("masked_mean")(m, *args, num_threads()) for m in metric.split("+")]
        elif metric == "ssim+l1":
            *values, grad = native("masked_ssim_l1_grad")(*args, *weights, num_threads())
        else:
            value, grad = native("masked_mean_grad")(metric, *args, *weights, num_threads())
            values = [value]
        if ctx.needs_input_grad[1]:
            ctx.save_for_backward(torch.from_numpy(grad))
        return torch.tensor(sum(w * v for w, v in zip(weights, values, strict=True)), dtype=dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_value):
        if grad_value is None or not ctx.needs_input_grad[1]:
            return None, None, None, None, None
        return None, _times(ctx.saved_tensors[0], grad_value), None, None, None


def _times(grad: torch.Tensor, grad_value: torch.Tensor) -> torch.Tensor:
    """A kernel's saved gradient times the incoming one: as computed when that is exactly 1
    (a weighted term of a summed loss), else scaled in numpy, single-threaded (a torch
    elementwise op pays thread start-up on a busy machine)."""
    factor = grad_value.item()
    if factor == 1.0:
        return grad
    return torch.from_numpy(grad.numpy() * grad.numpy().dtype.type(factor))


class _PixelL1(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, pixels, target, mask, weight):
        dtype = values.dtype
        value, grad = native("pixel_l1_grad")(
            to_numpy("values", values, dtype),
            to_numpy("pixels", pixels, torch.int64),
            to_numpy("target", target, dtype),
            to_numpy("mask", mask, dtype),
            weight,
            num_threads(),
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(torch.from_numpy(grad))
        return torch.tensor(weight * value, dtype=dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_value):
        if grad_value is None or not ctx.needs_input_grad[0]:
            return None, None, None, None, None
        return _times(ctx.saved_tensors[0], grad_value), None, None, None, None


def _check_weight(name: str, weight) -> None:
    """A loss term's weight: a finite number (not a bool)."""
    if (
        isinstance(weight, bool)
        or not isinstance(weight, (int, float))
        or not math.isfinite(weight)
    ):
        raise InvalidArgumentError(f"{name} must be a finite number, got {weight!r}")


def _check_constants(differentiated: str, tensors: dict, note: str = "") -> None:
    """Each of ``tensors`` (by argument name; None allowed) must not require grad: only
    ``differentiated`` gets a gradient."""
    for arg, t in tensors.items():
        if isinstance(t, torch.Tensor) and t.requires_grad:
            raise InvalidArgumentError(
                f"{arg} must not require grad: only {differentiated} is differentiated{note}"
            )


def _mask_as(mask: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``mask`` (float or bool) in the kernel's ``dtype``; an (H, W) mask is small next to
    the images, and numpy converts it without thread start-up."""
    if mask.dtype == dtype:
        return mask
    return torch.from_numpy(mask.detach().numpy().astype(_NUMPY_DTYPES[dtype]))


def _apply(metric: str, image, target, mask, weights: dict[str, float]) -> torch.Tensor:
    """``weights``: each metric's weight by its argument's name, in ``metric``'s order."""
    dtype = float_dtype("image", image)
    for name, weight in weights.items():
        _check_weight(name, weight)
    _check_constants(
        "image",
        {"target": target, "mask": mask},
        " (urhead.losses falls back to plain torch, differentiable in every input)",
    )
    if mask is not None:
        check_tensor("mask", mask)
        if mask.dtype in (torch.bool, torch.float32, torch.float64):
            mask = _mask_as(mask, dtype)
    return _MaskedImageComparison.apply(
        metric, image, target, mask, tuple(float(w) for w in weights.values())
    )


def masked_ssim(
    image: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    weight: float = 1.0,
) -> torch.Tensor:
    """Mean SSIM inside ``mask`` (a similarity: 1 for identical images) times ``weight``,
    differentiable in ``image``. Train with ``1 - masked_ssim(...)``, or with
    ``λ + masked_ssim(..., weight=-λ)`` as one term of a summed loss (no pass over the
    gradient to scale it).

    Per-pixel SSIM as :func:`urhead.ops._reference.ssim_map` (Gaussian window 11, σ = 1.5, zero
    padding, C1 = 0.01², C2 = 0.03², mean over channels), then ``Σ m·ssim / max(Σ m, 1)``.

    Args:
        image: (H, W, C) float32 or float64, contiguous, CPU.
        target: (H, W, C) of ``image``'s dtype; a constant (must not require grad).
        mask: (H, W) weights in [0, 1] (float or bool), or None for every pixel.
        weight: a finite factor of the value and its gradient (a loss term's weight).

    Returns:
        A 0-dim tensor of ``image``'s dtype. An all-zero mask gives 0 with zero gradient.
    """
    return _apply("ssim", image, target, mask, {"weight": weight})


def masked_l1(
    image: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    weight: float = 1.0,
) -> torch.Tensor:
    """Mean absolute difference inside ``mask`` times ``weight``:
    ``weight · Σ m·|image − target| / max(C·Σ m, 1)``,
    differentiable in ``image`` (subgradient sign(0) = 0). Arguments as :func:`masked_ssim`,
    but ``image`` may be (H, W, S) with S ≥ C, the target's channels: its first C are
    compared where they lie (a mesh's RGBA against an RGB frame, with no copy of its colour
    and no scatter of the gradient back into the RGBA); its gradient is zero past them."""
    return _apply("l1", image, target, mask, {"weight": weight})


def masked_ssim_l1(
    image: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    ssim_weight: float,
    l1_weight: float,
) -> torch.Tensor:
    """``ssim_weight · masked_ssim(...) + l1_weight · masked_l1(...)`` of the same images
    in one pass (the 3DGS photometric loss is ``λ + masked_ssim_l1(..., ssim_weight=-λ,
    l1_weight=1 - λ)``): the L1 rides in the SSIM gradient's pass, which reads both images
    anyway, and the two gradients come back as one. Each term's value and the summed
    gradient are bit for bit those of the two ops apart. Arguments as :func:`masked_ssim`
    (``image`` and ``target`` of the same channels)."""
    return _apply(
        "ssim+l1", image, target, mask, {"ssim_weight": ssim_weight, "l1_weight": l1_weight}
    )


def masked_pixel_l1(
    values: torch.Tensor,
    pixels: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    *,
    weight: float = 1.0,
) -> torch.Tensor:
    """Mean L1 distance, summed over channels, of values at listed pixels to an image, times
    ``weight``: ``weight · Σ_p w_p ‖v_p − target[x_p]‖₁ / max(Σ_p w_p, 1)`` with ``w_p``
    the mask at pixel ``x_p``, 0 where the target pixel is all zeros (no data) — the
    paper's normal loss over a mesh's covered pixels, one pass for the value and its
    gradient in place of a dozen torch ops. Differentiable in ``values`` (subgradient
    sign(0) = 0); sums in float64, the same bits for any thread count.

    Args:
        values: (P, C) float32 or float64, contiguous, CPU.
        pixels: (P,) int64 flat indices ``y·W + x``.
        target: (H, W, C) of ``values``' dtype; a constant.
        mask: (H, W) weights (float or bool); a constant.
        weight: a finite factor of the value and its gradient.

    Returns:
        A 0-dim tensor of ``values``' dtype (0 with zero gradient when no entry has weight).
    """
    dtype = float_dtype("values", values)
    _check_weight("weight", weight)
    check_tensor("target", target)
    check_tensor("mask", mask)
    _check_constants("values", {"target": target, "mask": mask})
    check_tensor("pixels", pixels)
    mask = _mask_as(mask, dtype)
    return _PixelL1.apply(
        values.contiguous(),
        pixels.contiguous(),
        target.contiguous(),
        mask.contiguous(),
        float(weight),
    )
