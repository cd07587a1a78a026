"""FLAME / SMPL linear blend skinning with a Rust forward and hand-written adjoint."""

from __future__ import annotations

from typing import NamedTuple

import torch

from urhead._threads import num_threads
from urhead.ops._bridge import float_dtype, from_numpy, grad_to_numpy, native, to_numpy


class LbsOutput(NamedTuple):
    verts: torch.Tensor
    """(B, V, 3) posed, translated vertices."""
    joints: torch.Tensor
    """(B, J, 3) posed, translated joints."""
    rotations: torch.Tensor
    """(B, V, 3, 3) linear part of each vertex's blended skinning transform. Carries
    rest-pose directions (normals) into the posed frame; re-normalise what it maps."""


class _Lbs(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, betas, pose, transl, v_template, shapedirs, posedirs, j_regressor, parents, lbs_weights
    ):
        dtype = betas.dtype
        tables = [
            to_numpy("v_template", v_template, dtype),
            to_numpy("shapedirs", shapedirs, dtype),
            to_numpy("posedirs", posedirs, dtype),
            to_numpy("j_regressor", j_regressor, dtype),
            to_numpy("parents", parents, torch.int32),
            to_numpy("lbs_weights", lbs_weights, dtype),
        ]
        args = [
            to_numpy("betas", betas, dtype),
            to_numpy("pose", pose, dtype),
            None if transl is None else to_numpy("transl", transl, dtype),
        ]
        out = native("lbs_forward")(*args, *tables, num_threads())
        verts, joints, rotations, v_shaped, v_posed, rest_joints = map(torch.from_numpy, out)
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(
            betas,
            pose,
            transl,
            v_template,
            shapedirs,
            posedirs,
            j_regressor,
            parents,
            lbs_weights,
            v_shaped,
            v_posed,
            rest_joints,
        )
        return verts, joints, rotations

    @staticmethod
    def backward(ctx, v_verts, v_joints, v_rotations):
        (
            betas,
            pose,
            transl,
            v_template,
            shapedirs,
            posedirs,
            j_regressor,
            parents,
            lbs_weights,
            v_shaped,
            v_posed,
            rest_joints,
        ) = ctx.saved_tensors
        dtype = betas.dtype
        need = ctx.needs_input_grad
        needs = (need[0], need[1], need[2], need[3], need[4])
        if not any(needs):
            return (None,) * 9
        grads = native("lbs_backward")(
            betas.numpy(),
            pose.numpy(),
            None if transl is None else transl.numpy(),
            v_template.numpy(),
            shapedirs.numpy(),
            posedirs.numpy(),
            j_regressor.numpy(),
            parents.numpy(),
            lbs_weights.numpy(),
            v_shaped.numpy(),
            v_posed.numpy(),
            rest_joints.numpy(),
            grad_to_numpy("v_verts", v_verts, dtype),
            grad_to_numpy("v_joints", v_joints, dtype),
            grad_to_numpy("v_rotations", v_rotations, dtype),
            needs,
            num_threads(),
        )
        return (*map(from_numpy, grads), None, None, None, None)


def lbs(
    betas: torch.Tensor,
    pose: torch.Tensor,
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    posedirs: torch.Tensor,
    j_regressor: torch.Tensor,
    parents: torch.Tensor,
    lbs_weights: torch.Tensor,
    transl: torch.Tensor | None = None,
) -> LbsOutput:
    """Linear blend skinning, as the ``lbs`` of the SMPL/FLAME code bases.

    Args:
        betas: (B, NB) shape and expression coefficients, against ``shapedirs``.
        pose: (B, J·3) axis-angle per joint (FLAME: global, neck, jaw, left eye, right eye).
        v_template: (V, 3) template vertices.
        shapedirs: (V, 3, NB) blendshape directions.
        posedirs: (9·(J−1), V·3) pose-corrective directions, against the flattened
            (R_j − I) of the non-root joints.
        j_regressor: (J, V) joint regressor (a sparse tensor is densified).
        parents: (J,) parent of each joint, ``parents[0] = -1``, ``parents[j] < j``.
        lbs_weights: (V, J) skinning weights.
        transl: (B, 3) translation added after skinning, or None.

    Returns:
        :class:`LbsOutput` ``(verts, joints, rotations)``.

    Gradients flow to ``betas``, ``pose``, ``transl``, and to ``v_template`` /
    ``shapedirs`` when those require grad; ``posedirs``, ``j_regressor`` and
    ``lbs_weights`` are constants. Inputs may be float32 or float64 (all alike), contiguous,
    on the CPU. Threads: ``URHEAD_NUM_THREADS`` or ``torch.get_num_threads()``.
    """
    float_dtype("betas", betas)
    if isinstance(j_regressor, torch.Tensor) and j_regressor.layout != torch.strided:
        j_regressor = j_regressor.to_dense()
    if isinstance(parents, torch.Tensor) and parents.dtype != torch.int32:
        parents = parents.to(torch.int32)  # (J,) is tiny; int64 is what FLAME code uses
    verts, joints, rotations = _Lbs.apply(
        betas, pose, transl, v_template, shapedirs, posedirs, j_regressor, parents, lbs_weights
    )
    return LbsOutput(verts, joints, rotations)
