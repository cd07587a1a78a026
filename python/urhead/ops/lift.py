"""The Gaussian lift — each Gaussian's geometry from its point on the posed surface — as one
Rust kernel with its hand-written adjoint (DESIGN.md step 4)."""

from __future__ import annotations

from typing import NamedTuple

import torch

from urhead._threads import num_threads
from urhead.errors import DTypeError, InvalidArgumentError, ShapeError
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


class LiftOutput(NamedTuple):
    means: torch.Tensor
    """(N, 3) world positions ``Σ_k b_k·v_k + lift·n̂``."""
    normals: torch.Tensor
    """(N, 3) posed unit normals n̂ (zero where the rest normal is zero)."""
    quats: torch.Tensor
    """(N, 4) unit quaternions (w, x, y, z) whose local z axis is n̂, as
    :func:`~urhead.ops.normal_to_quat`."""
    frames: torch.Tensor
    """(N, 3, 3) blended skinning rotations ``Σ_k b_k·R_k`` (rest frame → world); no
    gradient."""
    view_dirs: torch.Tensor
    """(N, 3) unit direction from the camera centre to each mean, in the rest frame:
    ``normalise(framesᵀ·normalise(means − centre))``; no gradient (SH colour's constant)."""


def lift_forward(verts, rotations, normals, lift, face_verts, bary, centre):
    """The native forward on contiguous tensors (no autograd): ``(means, normals, quats,
    frames, view_dirs)`` as :func:`lift_gaussians_geometry` returns them."""
    dtype = verts.dtype
    outputs = native("lift_gaussians_forward")(
        to_numpy("verts", verts, dtype),
        to_numpy("rotations", rotations, dtype),
        to_numpy("face_verts", face_verts, torch.int32),
        to_numpy("bary", bary, dtype),
        to_numpy("normals", normals, dtype),
        to_numpy("lift", lift, dtype),
        to_numpy("centre", centre, dtype),
        num_threads(),
    )
    return tuple(torch.from_numpy(x) for x in outputs)


def lift_backward(saved, v_means, v_normals, v_quats, needs):
    """The native adjoint: ``saved`` the forward's seven inputs, ``needs`` whether
    ``(verts, rotations, normals, lift)`` want a gradient; returns their gradients (None
    where not needed)."""
    verts, rotations, normals, lift, face_verts, bary, centre = saved
    dtype = verts.dtype
    grads = native("lift_gaussians_backward")(
        verts.detach().numpy(),
        rotations.detach().numpy(),
        face_verts.numpy(),
        bary.numpy(),
        normals.detach().numpy(),
        lift.detach().numpy(),
        centre.numpy(),
        grad_to_numpy("v_means", v_means, dtype),
        grad_to_numpy("v_normals", v_normals, dtype),
        grad_to_numpy("v_quats", v_quats, dtype),
        needs,
        num_threads(),
    )
    return tuple(map(from_numpy, grads))


def lift_tail_split(rows: torch.Tensor, start: int, offset: int | None):
    """The lift's maps out of the Gaussians' contiguous map rows ``(N, C)`` in one pass (no
    autograd): ``(normals (N, 3), lift (N,), raw scales (N, 3), raw opacities (N,),
    offset (N,) or None)`` from the tail at channel ``start`` (N, D, O, S, and the offset
    map E at tail channel ``offset``; the lift is D + E with one)."""
    out = native("lift_tail_split")(
        to_numpy("rows", rows, rows.dtype), start, offset, num_threads()
    )
    return tuple(map(from_numpy, out))


def lift_tail_grad(
    scales, opacities, channels, start, offset, v_normals, v_lift, v_scales, v_opacities, v_offset
):
    """The rows' tail gradient ``(N, channels − start)`` (no autograd) from the gradients of
    :func:`lift_tail_split`'s maps and the activations ``scales = exp(S)``, ``opacities =
    sigmoid(O)``; a ``None`` gradient contributes nothing (``v_normals`` and ``v_lift``
    come together)."""
    dtype = scales.dtype
    return torch.from_numpy(
        native("lift_tail_grad")(
            scales.numpy(),
            opacities.numpy(),
            channels,
            start,
            offset,
            grad_to_numpy("v_normals", v_normals, dtype),
            grad_to_numpy("v_lift", v_lift, dtype),
            grad_to_numpy("v_scales", v_scales, dtype),
            grad_to_numpy("v_opacities", v_opacities, dtype),
            grad_to_numpy("v_offset", v_offset, dtype),
            num_threads(),
        )
    )


class _LiftGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, verts, rotations, normals, lift, face_verts, bary, centre):
        means, posed, quats, frames, view_dirs = lift_forward(
            verts, rotations, normals, lift, face_verts, bary, centre
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(verts, rotations, normals, lift, face_verts, bary, centre)
        ctx.mark_non_differentiable(frames, view_dirs)
        return means, posed, quats, frames, view_dirs

    @staticmethod
    def backward(ctx, v_means, v_normals, v_quats, _v_frames, _v_dirs):
        needs = tuple(ctx.needs_input_grad[:4])
        if not any(needs) or (v_means is None and v_normals is None and v_quats is None):
            return (None,) * 7
        grads = lift_backward(ctx.saved_tensors, v_means, v_normals, v_quats, needs)
        return (*grads, None, None, None)


def lift_gaussians_geometry(
    verts: torch.Tensor,
    rotations: torch.Tensor,
    face_verts: torch.Tensor,
    bary: torch.Tensor,
    normals: torch.Tensor,
    lift: torch.Tensor,
    centre: torch.Tensor,
) -> LiftOutput:
    """Lifts Gaussians from their points on a posed mesh: positions, normals, rotations,
    frames and rest-frame view directions in one kernel.

    Gaussian j sits in a face with vertex ids ``face_verts[j]`` at barycentrics ``bary[j]``:

    - ``frames = Σ_k b_k·rotations[f_k]`` (the skinning rotations, blended);
    - ``n̂ = m / max(|m|, 1e-12)`` with ``m = frames·normals`` (a zero normal stays zero;
      the length is computed without overflow, so huge normals are normalised too);
    - ``means = Σ_k b_k·verts[f_k] + lift·n̂``;
    - ``quats = normal_to_quat(n̂)`` (:func:`urhead.ops.normal_to_quat`: Duff et al.'s
      branchless basis, identity with zero gradient for a zero or non-finite normal);
    - ``view_dirs = normalise(framesᵀ·normalise(means − centre))``.

    Args:
        verts: (V, 3) posed vertices, float32 or float64, finite.
        rotations: (V, 3, 3) per-vertex skinning rotations (rest frame → world), finite.
        face_verts: (N, 3) vertex ids of each Gaussian's face, int32 (other integer types
            are converted: pass int32 to avoid a copy per call); each in [0, V).
        bary: (N, 3) barycentrics, finite; a constant (must not require grad).
        normals: (N, 3) rest-frame normals, any length; zero, NaN and ±inf are allowed (a
            NaN normal gives a NaN mean and the identity quaternion).
        lift: (N,) distance along the posed normal (the displacement D, plus the offset E).
        centre: (3,) camera centre in world space, any float dtype; a constant.

    Returns:
        :class:`LiftOutput` ``(means, normals, quats, frames, view_dirs)``.

    Gradients flow from ``means``, ``normals`` and ``quats`` to ``verts``, ``rotations``
    (through the posed normal as well as the position), ``normals`` and ``lift``. A
    Gaussian with zero upstream gradient contributes exactly zero, even where its values
    are NaN. Vertex gradients are gathered per vertex in a fixed order: the same bits for
    any thread count. Threads: ``URHEAD_NUM_THREADS`` or ``torch.get_num_threads()``.
    """
    dtype = float_dtype("verts", verts)
    check_shape("verts", verts, 2, 3, "(V, 3)")
    for name, t, ndim, layout in (
        ("rotations", rotations, 3, "(V, 3, 3)"),
        ("bary", bary, 2, "(N, 3)"),
        ("normals", normals, 2, "(N, 3)"),
        ("lift", lift, 1, "(N,)"),
    ):
        check_tensor(name, t)
        if t.dtype != dtype:
            raise DTypeError(f"{name} must have the dtype of verts ({dtype}), got {t.dtype}")
        check_shape(name, t, ndim, None if ndim == 1 else 3, layout)
    if rotations.shape[1] != 3:
        raise ShapeError(f"rotations must be (V, 3, 3), got {tuple(rotations.shape)}")
    face_verts = index_tensor("face_verts", face_verts)
    check_shape("face_verts", face_verts, 2, 3, "(N, 3) int32")
    check_tensor("centre", centre)
    if not centre.is_floating_point():
        raise DTypeError(f"centre must be a float tensor, got {centre.dtype}")
    check_shape("centre", centre, 1, 3, "(3,)")
    for name, t in (("bary", bary), ("centre", centre)):
        if t.requires_grad:
            raise InvalidArgumentError(f"{name} must not require grad: it is a constant here")
    return LiftOutput(
        *_LiftGaussians.apply(
            verts.contiguous(),
            rotations.contiguous(),
            normals.contiguous(),
            lift.contiguous(),
            face_verts.contiguous(),
            bary.contiguous(),
            centre.to(dtype).contiguous(),
        )
    )
