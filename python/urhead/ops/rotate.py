"""Unit ``R·v`` (or ``Rᵀ·v``) for many 3×3 matrices and vectors, Rust forward and adjoint:
the avatar's posed normals and its camera rays in the rest frame, without torch's ``bmm``
(slow on batches of 3×3 matrices, its backward more so)."""

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


class _RotateNormalize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rotations, vectors, transpose, rows):
        dtype = rotations.dtype
        out = native("rotate_normalize_forward")(
            to_numpy("rotations", rotations, dtype),
            to_numpy("vectors", vectors, dtype),
            transpose,
            None if rows is None else to_numpy("rows", rows, torch.int64),
            num_threads(),
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(rotations, vectors, rows)
        ctx.transpose = transpose
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, v_out):
        needs = tuple(ctx.needs_input_grad[:2])
        if v_out is None or not any(needs):
            return None, None, None, None
        rotations, vectors, rows = ctx.saved_tensors
        v_rotations, v_vectors = native("rotate_normalize_backward")(
            rotations.detach().numpy(),
            vectors.detach().numpy(),
            ctx.transpose,
            None if rows is None else rows.numpy(),
            grad_to_numpy("v_out", v_out, rotations.dtype),
            needs,
            num_threads(),
        )
        return from_numpy(v_rotations), from_numpy(v_vectors), None, None


def rotate_normalize(
    rotations: torch.Tensor,
    vectors: torch.Tensor,
    transpose: bool = False,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """Each matrix applied to its vector, normalised: ``m / max(|m|, 1e-12)`` with
    ``m = R·v`` (``Rᵀ·v`` with ``transpose``), the same as
    ``m / m.norm(dim=-1, keepdim=True).clamp_min(1e-12)``.

    Args:
        rotations: (N, 3, 3) matrices, float32 or float64; rotations in practice, but any
            matrix is valid (the result is normalised after the product).
        vectors: (N, 3) vectors of the same dtype, any length.
        transpose: apply ``Rᵀ`` instead of ``R`` (a world direction into a rest frame).
        rows: optional (N,) int64 indices into ``vectors``, then an (M, 3) table: matrix
            ``i`` takes ``vectors[rows[i]]``, read in place — the values of
            ``vectors[rows]`` bit for bit, without the (N, 3) copy (a mesh's covered pixels
            pick their camera rays from the whole image's table). The table gets no
            gradient, so it must not require one.

    Returns:
        (N, 3) unit vectors, or ``m / 1e-12`` below the floor (a zero product stays
        zero). ``|m|`` is computed without
        overflow, so huge products are normalised too (float32 beyond ~1.8e19, where the
        torch expression's ``|m|`` overflows and gives zero).

    Gradients flow to ``rotations`` and ``vectors`` (only those that require it), as the
    torch expression's: with ``u`` the output and ``g`` its gradient, ``(g − (g·u)·u)/|m|``
    to ``m`` for ``|m| ≥ 1e-12``, ``g/1e-12`` below (so a zero product passes ``1e12·g``).
    Non-finite values are data, not errors: a row with a NaN product gives a NaN output,
    an infinite one NaN where it is infinite; either gives NaN gradients to the row's
    inputs, even for a zero upstream gradient (as the torch expression does); other rows
    are unaffected. Every row is independent: the same bits for any thread count.
    Threads: ``URHEAD_NUM_THREADS`` or ``torch.get_num_threads()``.
    """
    dtype = float_dtype("rotations", rotations)
    check_shape("rotations", rotations, 3, 3, "(N, 3, 3)")
    if rotations.shape[1] != 3:
        raise ShapeError(f"rotations must be (N, 3, 3), got {tuple(rotations.shape)}")
    check_tensor("vectors", vectors)
    if vectors.dtype != dtype:
        raise DTypeError(f"vectors must have the dtype of rotations ({dtype}), got {vectors.dtype}")
    check_shape("vectors", vectors, 2, 3, "(N, 3)" if rows is None else "(M, 3)")
    if rows is not None:
        check_tensor("rows", rows)
        if rows.dtype != torch.int64:
            raise DTypeError(f"rows must be int64, got {rows.dtype}")
        check_shape("rows", rows, 1, None, "(N,) int64")
        if vectors.requires_grad:
            raise InvalidArgumentError(
                "vectors picked by rows get no gradient; pass a table that does not require one"
            )
        rows = rows.contiguous()
    return _RotateNormalize.apply(
        rotations.contiguous(), vectors.contiguous(), bool(transpose), rows
    )
