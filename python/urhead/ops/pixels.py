"""From a rasterized image to its covered pixels and back, Rust forward and adjoint: the
mesh branch shades only the pixels a triangle covers (as torch ops, the list is a mask
image plus a serial ``nonzero``, and the image back a ``repeat`` plus an ``index_put_``:
~2 ms of a 512² frame, serial)."""

from __future__ import annotations

import torch

from urhead._threads import num_threads
from urhead.errors import DTypeError, ShapeError
from urhead.ops._bridge import (
    check_shape,
    check_tensor,
    float_dtype,
    from_numpy,
    grad_to_numpy,
    native,
    to_numpy,
)


def covered_pixels(tri_id: torch.Tensor) -> torch.Tensor:
    """The pixels a triangle covers.

    Args:
        tri_id: (H, W) int32 triangle per pixel, −1 where empty (``rasterize``'s).

    Returns:
        (P,) int64 flat indices ``y·W + x`` of the pixels with ``tri_id ≥ 0``, increasing:
        ``(tri_id.reshape(-1) >= 0).nonzero()[:, 0]``.
    """
    check_tensor("tri_id", tri_id)
    check_shape("tri_id", tri_id, 2, None, "(H, W) int32")
    out = native("covered_pixels")(
        to_numpy("tri_id", tri_id.contiguous(), torch.int32), num_threads()
    )
    return torch.from_numpy(out)


class _ScatterPixels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, pixels, background, size):
        dtype = values.dtype
        out = native("scatter_pixels_forward")(
            to_numpy("values", values, dtype),
            to_numpy("pixels", pixels, torch.int64),
            to_numpy("background", background, dtype),
            size,
            num_threads(),
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(pixels)
        ctx.dtype = dtype
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, v_image):
        needs = (ctx.needs_input_grad[0], ctx.needs_input_grad[2])
        if v_image is None or not any(needs):
            return None, None, None, None
        (pixels,) = ctx.saved_tensors
        v_values, v_background = native("scatter_pixels_backward")(
            pixels.numpy(), grad_to_numpy("v_image", v_image, ctx.dtype), needs, num_threads()
        )
        return from_numpy(v_values), None, from_numpy(v_background), None


def scatter_pixels(
    values: torch.Tensor, pixels: torch.Tensor, background: torch.Tensor, size: tuple[int, int]
) -> torch.Tensor:
    """An image of ``background`` with the listed pixels set to their rows.

    Args:
        values: (P, C) float32 or float64 rows, one per listed pixel.
        pixels: (P,) int64 flat indices ``y·W + x``, strictly increasing (each pixel once,
            as :func:`covered_pixels` lists them).
        background: (C,) the value of every other pixel, ``values``' dtype.
        size: ``(H, W)``.

    Returns:
        (H, W, C). Gradients flow to ``values`` (the image's gradient at the listed
        pixels) and ``background`` (summed over the others); non-finite values are data.
        The same bits for any thread count.
    """
    dtype = float_dtype("values", values)
    check_shape("values", values, 2, None, "(P, C)")
    check_tensor("pixels", pixels)
    check_shape("pixels", pixels, 1, None, "(P,) int64")
    check_tensor("background", background)
    if background.dtype != dtype:
        raise DTypeError(
            f"background must have the dtype of values ({dtype}), got {background.dtype}"
        )
    if background.shape != (values.shape[1],):
        raise ShapeError(
            f"background must be (C,) = ({values.shape[1]},), got {tuple(background.shape)}"
        )
    if pixels.shape[0] != values.shape[0]:
        raise ShapeError(
            f"pixels must list one pixel per row of values ({values.shape[0]}), "
            f"got {pixels.shape[0]}"
        )
    height, width = (int(x) for x in size)
    return _ScatterPixels.apply(
        values.contiguous(), pixels.contiguous(), background.contiguous(), (height, width)
    )
