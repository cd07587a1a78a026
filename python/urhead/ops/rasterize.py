"""Mesh rasterization with a Rust forward and hand-written adjoint (nvdiffrast-style)."""

from __future__ import annotations

from typing import NamedTuple

import torch

from urhead._threads import num_threads
from urhead.camera import Camera
from urhead.errors import DTypeError, ShapeError
from urhead.ops._bridge import (
    check_camera,
    check_shape,
    float_dtype,
    grad_to_numpy,
    index_tensor,
    native,
    to_numpy,
)


class RasterOutput(NamedTuple):
    tri_id: torch.Tensor
    """(H, W) int32 index of the triangle covering each pixel centre, -1 where empty."""
    bary: torch.Tensor
    """(H, W, 2) perspective-correct barycentrics of the triangle's 2nd and 3rd vertex
    (the 1st vertex weighs 1 - b1 - b2); 0 where empty. Differentiable."""
    depth: torch.Tensor
    """(H, W) linear view-space depth (camera z), +inf where empty. Not differentiable."""


class UvRasterOutput(NamedTuple):
    tri_id: torch.Tensor
    """(H, W) int32 index of the UV triangle covering each texel centre, -1 where empty."""
    bary: torch.Tensor
    """(H, W, 2) barycentrics (affine in UV) of the triangle's 2nd and 3rd vertex."""


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, faces, camera):
        dtype = verts.dtype
        *out, state = native("rasterize_forward")(
            to_numpy("verts", verts, dtype),
            to_numpy("faces", faces, torch.int32),
            camera.core_args(),
            num_threads(),
        )
        tri_id, bary, depth = map(torch.from_numpy, out)
        ctx.mark_non_differentiable(tri_id, depth)
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(verts, faces, tri_id)
        ctx.camera = camera
        # The triangles' setup, kept so that the backward does not set them up again.
        ctx.state = state if ctx.needs_input_grad[0] else None
        return tri_id, bary, depth

    @staticmethod
    def backward(ctx, _v_tri_id, v_bary, _v_depth):
        if v_bary is None or not ctx.needs_input_grad[0]:
            return None, None, None
        verts, faces, tri_id = ctx.saved_tensors
        dtype = verts.dtype
        v_verts = native("rasterize_backward")(
            ctx.state,
            verts.detach().numpy(),
            faces.numpy(),
            ctx.camera.core_args(),
            tri_id.numpy(),
            grad_to_numpy("v_bary", v_bary, dtype),
            num_threads(),
        )
        return torch.from_numpy(v_verts), None, None


def rasterize(verts: torch.Tensor, faces: torch.Tensor, camera: Camera) -> RasterOutput:
    """Rasterizes a triangle mesh through a pinhole camera.

    Args:
        verts: (V, 3) world-space vertex positions, float32 or float64.
        faces: (F, 3) int32 vertex indices (other integer dtypes are converted).
        camera: a :class:`urhead.Camera`; the image is ``(camera.height, camera.width)``.

    Returns:
        :class:`RasterOutput` ``(tri_id, bary, depth)``.

    Semantics (as nvdiffrast, on the CPU): each pixel is sampled at its centre; coverage is
    watertight (screen positions snapped to 1/256 px, exact integer edge functions, top-left
    rule), both facings are drawn; triangles are clipped against ``z = camera.near`` in
    camera space and barycentrics refer to the unclipped triangle; pixels deeper than
    ``camera.far`` stay empty; the nearest triangle wins and equal depths go to the lower
    triangle id. Barycentrics are clamped to the simplex.

    Gradients flow from ``bary`` to ``verts`` (the barycentrics' dependence on the vertex
    positions through the projection, as nvdiffrast's rasterize gradient); coverage and
    ``depth`` are not differentiated — use :func:`urhead.ops.antialias` for silhouette
    gradients. Threads: ``URHEAD_NUM_THREADS`` or ``torch.get_num_threads()``.
    """
    float_dtype("verts", verts)
    check_shape("verts", verts, 2, 3, "(V, 3)")
    faces = index_tensor("faces", faces)
    check_shape("faces", faces, 2, 3, "(F, 3) int32")
    tri_id, bary, depth = _Rasterize.apply(verts, faces, check_camera(camera))
    return RasterOutput(tri_id, bary, depth)


def rasterize_uv(
    uv_coords: torch.Tensor, uv_faces: torch.Tensor, height: int, width: int
) -> UvRasterOutput:
    """Rasterizes the mesh's UV layout: for each texel centre of a ``(height, width)`` map,
    the UV triangle covering it and its barycentrics. No gradient.

    Args:
        uv_coords: (T, 2) UV coordinates, OBJ convention (u right, v up), float32/float64.
        uv_faces: (F, 3) int32 indices into ``uv_coords``; triangle ids match the geometry
            faces when the UV faces are listed in the same order.
        height, width: texel grid size; texel (r, c) has its centre at
            u = (c + 0.5) / width, v = 1 - (r + 0.5) / height (row 0 is v = 1).

    Returns:
        :class:`UvRasterOutput` ``(tri_id, bary)``. Coverage follows the same watertight
        rules as :func:`rasterize`; where islands overlap the lower triangle id wins.
    """
    dtype = float_dtype("uv_coords", uv_coords)
    check_shape("uv_coords", uv_coords, 2, 2, "(T, 2)")
    uv_faces = index_tensor("uv_faces", uv_faces)
    check_shape("uv_faces", uv_faces, 2, 3, "(F, 3) int32")
    for name, side in (("height", height), ("width", width)):
        if isinstance(side, bool) or not isinstance(side, int):
            raise DTypeError(f"{name} must be an int, got {type(side).__name__}")
        if side < 1:
            raise ShapeError(f"{name} must be ≥ 1, got {side}")
    tri_id, bary = native("rasterize_uv")(
        to_numpy("uv_coords", uv_coords, dtype),
        to_numpy("uv_faces", uv_faces, torch.int32),
        height,
        width,
        num_threads(),
    )
    return UvRasterOutput(torch.from_numpy(tri_id), torch.from_numpy(bary))
