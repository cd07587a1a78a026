"""From a rasterized image to its covered pixels and back, Rust forward and adjoint: the
mesh branch shades only the pixels a triangle covers (as torch ops, the list is a mask
image plus a serial ``nonzero``, and the image back a ``repeat`` plus an ``index_put_``:
~2 ms of a 512² frame, serial)."""

from __future__ import annotations

import torch

from urhead._threads import num_threads
from urhead.errors import DTypeError, InvalidArgumentError, ShapeError
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
    def forward(ctx, values, pixels, fill, background, size):
        dtype = values.dtype
        out = native("scatter_pixels_forward")(
            to_numpy("values", values, dtype),
            to_numpy("pixels", pixels, torch.int64),
            to_numpy("fill", fill, dtype),
            to_numpy("background", background, dtype),
            size,
            num_threads(),
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(pixels)
        ctx.dtype, ctx.fill = dtype, fill.shape[0]
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, v_image):
        needs = (ctx.needs_input_grad[0], ctx.needs_input_grad[3])
        if v_image is None or not any(needs):
            return None, None, None, None, None
        (pixels,) = ctx.saved_tensors
        v_values, v_background = native("scatter_pixels_backward")(
            pixels.numpy(),
            grad_to_numpy("v_image", v_image, ctx.dtype),
            ctx.fill,
            needs,
            num_threads(),
        )
        return from_numpy(v_values), None, None, from_numpy(v_background), None


def scatter_pixels(
    values: torch.Tensor,
    pixels: torch.Tensor,
    background: torch.Tensor,
    size: tuple[int, int],
    fill: torch.Tensor | None = None,
) -> torch.Tensor:
    """An image of ``background`` with the listed pixels set to their rows.

    Args:
        values: (P, C − K) float32 or float64 rows, one per listed pixel.
        pixels: (P,) int64 flat indices ``y·W + x``, strictly increasing (each pixel once,
            as :func:`covered_pixels` lists them).
        background: (C,) the value of every other pixel, ``values``' dtype.
        size: ``(H, W)``.
        fill: (K,) a constant the listed pixels' last K channels take (e.g. alpha 1 after
            a colour), ``values``' dtype; no gradient. None: K = 0. Saves concatenating it
            to every row (and slicing the rows' gradient back out).

    Returns:
        (H, W, C). Gradients flow to ``values`` (the image's gradient at the listed
        pixels, less the fill's channels) and ``background`` (summed over the others);
        non-finite values are data. The same bits for any thread count.
    """
    dtype = float_dtype("values", values)
    check_shape("values", values, 2, None, "(P, C − K)")
    check_tensor("pixels", pixels)
    check_shape("pixels", pixels, 1, None, "(P,) int64")
    if fill is None:
        fill = values.new_zeros(0)
    for name, tensor in (("fill", fill), ("background", background)):
        check_tensor(name, tensor)
        if tensor.dtype != dtype:
            raise DTypeError(f"{name} must have the dtype of values ({dtype}), got {tensor.dtype}")
    check_shape("fill", fill, 1, None, "(K,)")
    if fill.requires_grad:
        raise InvalidArgumentError("fill is a constant: pass it detached (it gets no gradient)")
    channels = values.shape[1] + fill.shape[0]
    if background.shape != (channels,):
        raise ShapeError(
            f"background must be (C,) = ({channels},) (values' {values.shape[1]} channels "
            f"and fill's {fill.shape[0]}), got {tuple(background.shape)}"
        )
    if pixels.shape[0] != values.shape[0]:
        raise ShapeError(
            f"pixels must list one pixel per row of values ({values.shape[0]}), "
            f"got {pixels.shape[0]}"
        )
    height, width = (int(x) for x in size)
    return _ScatterPixels.apply(
        values.contiguous(),
        pixels.contiguous(),
        fill.contiguous(),
        background.contiguous(),
        (height, width),
    )
