"""Batched spherical-harmonics colour along fixed view directions, Rust forward and
adjoint (to the coefficients only)."""

from __future__ import annotations

import torch

from urhead._threads import num_threads
from urhead.errors import DTypeError, InvalidArgumentError
from urhead.ops._bridge import check_shape, float_dtype, grad_to_numpy, native, to_numpy


def sh_shade_forward(coeffs, dirs, degree):
    """The native forward on contiguous tensors (no autograd): (P, 3) colours."""
    dtype = coeffs.dtype
    rgb = native("sh_shade_forward")(
        to_numpy("coeffs", coeffs, dtype), to_numpy("dirs", dirs, dtype), degree, num_threads()
    )
    return torch.from_numpy(rgb)


def sh_shade_backward(coeffs, dirs, degree, v_rgb, rest=None):
    """The native adjoint: (P, S) gradient of the rows ``coeffs``, zero past the colour —
    or, with ``rest = (values (P, W), start)``, those values at channels
    ``start..start + W`` (the rows' other consumers' gradient, written in the same pass)."""
    dtype = coeffs.dtype
    if rest is not None:
        rest = (to_numpy("rest", rest[0], dtype), rest[1])
    v_coeffs = native("sh_shade_backward")(
        coeffs.detach().numpy(),
        dirs.detach().numpy(),
        degree,
        grad_to_numpy("v_rgb", v_rgb, dtype),
        rest,
        num_threads(),
    )
    return torch.from_numpy(v_coeffs)


class _ShShade(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coeffs, dirs, degree):
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(coeffs, dirs)
        ctx.degree = degree
        return sh_shade_forward(coeffs, dirs, degree)

    @staticmethod
    def backward(ctx, v_rgb):
        if v_rgb is None or not ctx.needs_input_grad[0]:
            return None, None, None
        coeffs, dirs = ctx.saved_tensors
        return sh_shade_backward(coeffs, dirs, ctx.degree, v_rgb), None, None


def sh_shade(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Colours ``max(Σ_k b_k(dir)·c_k + 0.5, 0)`` of many samples (3DGS SH constants).

    Args:
        coeffs: (P, S) rows whose first 3·(degree + 1)² entries are the SH coefficients,
            coefficient-major (entry 3k + c is coefficient k of colour c); the rest of a
            row is ignored, so a packed table of map samples needs no slicing or copy.
        dirs: (P, 3) unit view directions; constants (no gradient flows to them).
        degree: 0–3.

    Returns:
        (P, 3) colours. Gradient: to ``coeffs`` (zero past the colour entries and where a
        channel is clamped at 0). A NaN coefficient gives a NaN colour.
    """
    dtype = float_dtype("coeffs", coeffs)
    check_shape("coeffs", coeffs, 2, None, "(P, S)")
    if dirs.dtype != dtype:
        raise DTypeError(f"dirs must have the dtype of coeffs ({dtype}), got {dirs.dtype}")
    check_shape("dirs", dirs, 2, 3, "(P, 3)")
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= 3:
        raise InvalidArgumentError(f"degree must be an int in [0, 3], got {degree!r}")
    return _ShShade.apply(coeffs.contiguous(), dirs.detach().contiguous(), degree)
