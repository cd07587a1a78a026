"""Attribute interpolation over a rasterized mesh, Rust forward and adjoint."""

from __future__ import annotations

import torch

from urhead._threads import num_threads
from urhead.errors import DTypeError
from urhead.ops._bridge import (
    check_shape,
    check_tensor,
    float_dtype,
    from_numpy,
    grad_to_numpy,
    index_tensor,
    native,
    to_numpy,
)
from urhead.ops.rasterize import RasterOutput, UvRasterOutput


class _Interpolate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, attr, bary, tri_id, faces, pixels):
        dtype = attr.dtype
        out = native("interpolate_forward")(
            to_numpy("attr", attr, dtype),
            to_numpy("faces", faces, torch.int32),
            to_numpy("tri_id", tri_id, torch.int32),
            to_numpy("bary", bary, dtype),
            None if pixels is None else to_numpy("pixels", pixels, torch.int64),
            num_threads(),
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(attr, bary, tri_id, faces, pixels)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, v_out):
        needs = (ctx.needs_input_grad[0], ctx.needs_input_grad[1])
        if v_out is None or not any(needs):
            return None, None, None, None, None
        attr, bary, tri_id, faces, pixels = ctx.saved_tensors
        dtype = attr.dtype
        v_attr, v_bary = native("interpolate_backward")(
            attr.detach().numpy(),
            faces.numpy(),
            tri_id.numpy(),
            bary.detach().numpy(),
            None if pixels is None else pixels.numpy(),
            grad_to_numpy("v_out", v_out, dtype),
            needs,
            num_threads(),
        )
        return from_numpy(v_attr), from_numpy(v_bary), None, None, None


def interpolate(
    attr: torch.Tensor,
    raster: RasterOutput | UvRasterOutput,
    faces: torch.Tensor,
    pixels: torch.Tensor | None = None,
) -> torch.Tensor:
    """Interpolates per-vertex attributes over the rasterized triangles.

    Args:
        attr: (V, C) attributes, same dtype as ``raster.bary``.
        raster: the output of :func:`urhead.ops.rasterize` (or ``rasterize_uv``).
        faces: (F, 3) int32 indices into ``attr``, triangle-for-triangle with the faces
            that were rasterized: the geometry faces for per-vertex attributes, the UV
            faces for UV coordinates.
        pixels: optional (P,) int64 flat pixel indices ``y·W + x``, contiguous, in any
            order, repeats allowed: interpolate at these pixels only. The same values,
            bit for bit, as the whole image indexed at them, without building the image
            (nor, backward, its (H, W, C) gradient).

    Returns:
        (H, W, C), or (P, C) with ``pixels``: ``(1 - b1 - b2)·attr[f0] + b1·attr[f1] +
        b2·attr[f2]``, 0 where empty.

    Gradients flow to ``attr`` and, through ``raster.bary``, to the rasterized vertices.
    With ``pixels`` the barycentric gradient is nonzero at the listed pixels only (a
    repeated pixel receives the sum); the attribute gradient is the whole image's up to
    summation order, and bit for bit the same when ``pixels`` lists every covered pixel in
    increasing order (``(raster.tri_id.reshape(-1) >= 0).nonzero()[:, 0]``).
    """
    dtype = float_dtype("attr", attr)
    check_shape("attr", attr, 2, None, "(V, C)")
    if raster.bary.dtype != dtype:
        raise DTypeError(
            f"attr must have the dtype of raster.bary ({raster.bary.dtype}), got {dtype}"
        )
    faces = index_tensor("faces", faces)
    check_shape("faces", faces, 2, 3, "(F, 3) int32")
    if pixels is not None:
        check_tensor("pixels", pixels)
        check_shape("pixels", pixels, 1, None, "(P,) int64")
    return _Interpolate.apply(attr, raster.bary, raster.tri_id, faces, pixels)
