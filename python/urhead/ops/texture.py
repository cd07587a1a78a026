"""Bilinear texture sampling with a sparse texture gradient, Rust forward and adjoint."""

from __future__ import annotations

import torch

from urhead._threads import num_threads
from urhead.errors import DTypeError
from urhead.ops._bridge import check_shape, float_dtype, from_numpy, grad_to_numpy, kernel, to_numpy


class _Texture(torch.autograd.Function):
    @staticmethod
    def forward(ctx, tex, uv, sparse_grad):
        dtype = tex.dtype
        flat_uv = uv.reshape(-1, 2) if uv.is_contiguous() else uv
        out = kernel("texture_forward", dtype)(
            to_numpy("tex", tex, dtype), to_numpy("uv", flat_uv, dtype), num_threads()
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(tex, uv)
        ctx.sparse_grad = sparse_grad
        return torch.from_numpy(out).reshape(*uv.shape[:-1], tex.shape[-1])

    @staticmethod
    def backward(ctx, v_out):
        needs = (ctx.needs_input_grad[0], ctx.needs_input_grad[1])
        if v_out is None or not any(needs):
            return None, None, None
        tex, uv = ctx.saved_tensors
        dtype = tex.dtype
        channels = tex.shape[-1]
        indices, values, v_uv = kernel("texture_backward", dtype)(
            tex.detach().numpy(),
            uv.detach().reshape(-1, 2).numpy(),
            grad_to_numpy("v_out", v_out.reshape(-1, channels), dtype),
            needs,
            num_threads(),
        )
        v_tex = None
        if indices is not None:
            v_tex = torch.sparse_coo_tensor(
                torch.from_numpy(indices),
                torch.from_numpy(values),
                tex.shape,
                is_coalesced=True,
                check_invariants=False,
            )
            if not ctx.sparse_grad:
                v_tex = v_tex.to_dense()
        v_uv = from_numpy(v_uv)
        return v_tex, None if v_uv is None else v_uv.reshape(uv.shape), None


def texture(tex: torch.Tensor, uv: torch.Tensor, *, sparse_grad: bool = True) -> torch.Tensor:
    """Bilinear texture lookup.

    Args:
        tex: (Ht, Wt, C) texture, float32 or float64, contiguous.
        uv: (..., 2) texture coordinates, same dtype, contiguous. OBJ convention: u runs
            left → right, v bottom → top, texel row 0 is the top (v = 1); texel (r, c) has
            its centre at u = (c + 0.5)/Wt, v = 1 - (r + 0.5)/Ht.
        sparse_grad: return the texture gradient as a sparse COO tensor (default). With
            False it is densified — this allocates a full (Ht, Wt, C) tensor; use it only
            for small textures.

    Returns:
        (..., C) samples.

    Addressing is clamp-to-edge (outside the texel centres the edge texels are used, and
    the UV gradient is zero there): wrapping would bleed across UV-atlas islands. A sample
    whose u or v is NaN or ±inf returns zeros and passes no gradient.

    Gradients: to ``uv``, and to ``tex`` as a coalesced sparse COO tensor of size
    ``tex.shape`` with 2 sparse dimensions (texel row, column; sorted, unique) and dense
    values (K, C) — the contract of ``nn.Embedding(sparse=True)``, so
    ``torch.optim.SparseAdam`` consumes it directly. It lists exactly the texels given a
    non-zero bilinear weight by a sample with a finite UV and a non-zero output gradient;
    no dense (Ht, Wt, C) buffer is ever allocated. ``tex`` should be a leaf tensor (a
    parameter): most autograd ops cannot propagate a sparse gradient further. Note that
    torch's accumulation into ``tex.grad`` keeps the sorted indices but drops the coalesced
    flag, so ``SparseAdam`` would sort them again; re-mark the gradient to skip that:
    ``p.grad = torch.sparse_coo_tensor(g._indices(), g._values(), g.shape,
    is_coalesced=True)`` with ``g = p.grad``.
    """
    dtype = float_dtype("tex", tex)
    check_shape("tex", tex, 3, None, "(Ht, Wt, C)")
    float_dtype("uv", uv)
    if uv.dtype != dtype:
        raise DTypeError(f"uv must have the dtype of tex ({dtype}), got {uv.dtype}")
    if uv.dim() < 1 or uv.shape[-1] != 2:
        check_shape("uv", uv, max(uv.dim(), 1), 2, "(..., 2)")
    return _Texture.apply(tex, uv, sparse_grad)
