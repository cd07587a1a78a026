"""Bilinear texture sampling with a sparse texture gradient, Rust forward and adjoint."""

from __future__ import annotations

import numpy as np
import torch

from urhead._threads import num_threads
from urhead.errors import DTypeError
from urhead.ops._bridge import check_shape, float_dtype, from_numpy, grad_to_numpy, native, to_numpy


def _sample(tex: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """The Rust bilinear lookup: (Ht, Wt, C) at (..., 2) → (..., C)."""
    dtype = tex.dtype
    flat_uv = uv.reshape(-1, 2) if uv.is_contiguous() else uv
    out = native("texture_forward")(
        to_numpy("tex", tex, dtype), to_numpy("uv", flat_uv, dtype), num_threads()
    )
    return torch.from_numpy(out).reshape(*uv.shape[:-1], tex.shape[-1])


def _check_lookup(tex: torch.Tensor, uv: torch.Tensor) -> None:
    dtype = float_dtype("tex", tex)
    check_shape("tex", tex, 3, None, "(Ht, Wt, C)")
    float_dtype("uv", uv)
    if uv.dtype != dtype:
        raise DTypeError(f"uv must have the dtype of tex ({dtype}), got {uv.dtype}")
    if uv.dim() < 1 or uv.shape[-1] != 2:
        check_shape("uv", uv, max(uv.dim(), 1), 2, "(..., 2)")


class _Texture(torch.autograd.Function):
    @staticmethod
    def forward(ctx, tex, uv, sparse_grad):
        out = _sample(tex, uv)
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(tex, uv)
        ctx.sparse_grad = sparse_grad
        return out

    @staticmethod
    def backward(ctx, v_out):
        needs = (ctx.needs_input_grad[0], ctx.needs_input_grad[1])
        if v_out is None or not any(needs):
            return None, None, None
        tex, uv = ctx.saved_tensors
        dtype = tex.dtype
        channels = tex.shape[-1]
        indices, values, v_uv = native("texture_backward")(
            tex.detach().numpy(),
            uv.detach().reshape(-1, 2).numpy(),
            grad_to_numpy("v_out", v_out.reshape(-1, channels), dtype),
            needs,
            num_threads(),
        )
        v_tex = None
        if indices is not None:
            v_tex = _sparse_gradient(indices, values, tex.shape)
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
    _check_lookup(tex, uv)
    return _Texture.apply(tex, uv, sparse_grad)


class _GatheredTexture(torch.autograd.Function):
    """Samples like :func:`texture`; the texture's gradient is recorded in ``gather`` instead
    of flowing back through autograd (the UV gradient flows as usual). ``tex`` is an input
    only so the samples require grad when it does; it receives None."""

    @staticmethod
    def forward(ctx, uv, tex, gather):
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(uv)
        ctx.gather = gather
        return _sample(gather.tex, uv)

    @staticmethod
    def backward(ctx, v_out):
        if v_out is None:
            return None, None, None
        (uv,) = ctx.saved_tensors
        gather = ctx.gather
        channels = gather.tex.shape[-1]
        v_out = v_out.reshape(-1, channels).contiguous()
        flat_uv = uv.detach().reshape(-1, 2)
        gather.record(flat_uv, v_out)
        if not ctx.needs_input_grad[0]:
            return None, None, None
        _, _, v_uv = native("texture_backward")(
            gather.tex.numpy(),
            flat_uv.numpy(),
            grad_to_numpy("v_out", v_out, gather.tex.dtype),
            (False, True),
            num_threads(),
        )
        return from_numpy(v_uv).reshape(uv.shape), None, None


class TextureGather:
    """One texture, several lookups, one gradient.

    Autograd sums the sparse gradients of separate :func:`texture` calls on the same table
    by sparse addition, then an optimiser coalesces the sum again — for a 2048² × 56 map
    looked up at ~100k points per iteration that bookkeeping costs more than the lookups.
    Here each :meth:`sample` records its output gradient during the backward pass, and
    :meth:`gradient` turns all of them into one coalesced sparse COO gradient with a single
    kernel call (the same tensor :func:`texture` would give for the union of the lookups).

    Args:
        tex: (Ht, Wt, C) texture, usually a parameter with ``requires_grad`` (samples then
            require grad).
        accumulate: at the end of each backward pass that reached a lookup, add the
            lookups' gradient (:meth:`gradient`) to ``tex.grad`` as a leaf parameter's
            would be; otherwise ``tex.grad`` is left alone and :meth:`gradient` hands it out.
    """

    def __init__(self, tex: torch.Tensor, *, accumulate: bool = False):
        float_dtype("tex", tex)
        check_shape("tex", tex, 3, None, "(Ht, Wt, C)")
        self.source = tex  # an input of every lookup, so samples require grad when it does
        self.tex = tex.detach()
        self.accumulate = accumulate
        self._uv: list[torch.Tensor] = []
        self._grad: list[torch.Tensor] = []

    def sample(self, uv: torch.Tensor) -> torch.Tensor:
        """(..., 2) UVs → (..., C) samples, as :func:`texture`; differentiable in ``uv``."""
        _check_lookup(self.tex, uv)
        return _GatheredTexture.apply(uv.contiguous(), self.source, self)

    def record(self, uv: torch.Tensor, v_out: torch.Tensor) -> None:
        if self.accumulate and not self._uv:
            # The first lookup this pass: one kernel call once every lookup has recorded.
            torch.autograd.Variable._execution_engine.queue_callback(self._accumulate)
        self._uv.append(uv)
        self._grad.append(v_out)

    def _accumulate(self) -> None:
        grad = self.gradient()
        if grad is None:
            return
        source = self.source
        source.grad = grad if source.grad is None else source.grad + grad

    def samples(self) -> list[tuple[torch.Tensor, torch.Tensor]] | None:
        """The recorded lookups, one ``(uv (M_i, 2), v_out (M_i, C))`` segment each in
        recording order, contiguous: the texture gradient before it is built (None when
        nothing was recorded); clears the record.
        :meth:`urhead.optim.SparseAdam.step_reported` applies it without building it, or
        joining the segments (at the paper's settings ~100k × 56 floats a step)."""
        if not self._uv:
            return None
        segments = list(zip(self._uv, self._grad, strict=True))
        self._uv.clear()
        self._grad.clear()
        return segments

    def gradient(self) -> torch.Tensor | None:
        """The recorded lookups' texture gradient as a coalesced sparse COO tensor of
        ``tex.shape`` (None when nothing was recorded); clears the record."""
        segments = self.samples()
        if segments is None:
            return None
        uv, v_out = (torch.cat(arrays) for arrays in zip(*segments, strict=True))
        dtype = self.tex.dtype
        return texture_gradient(self.tex, uv, grad_to_numpy("v_out", v_out, dtype))


def texture_gradient(tex: torch.Tensor, uv: torch.Tensor, v_out: np.ndarray) -> torch.Tensor:
    """The coalesced sparse COO gradient of ``tex (Ht, Wt, C)`` from lookups at
    ``uv (N, 2)`` whose output gradient is ``v_out (N, C)``."""
    indices, values, _ = native("texture_backward")(
        tex.detach().numpy(), uv.detach().numpy(), v_out, (True, False), num_threads()
    )
    return _sparse_gradient(indices, values, tex.shape)


def _sparse_gradient(indices: np.ndarray, values: np.ndarray, shape) -> torch.Tensor:
    return torch.sparse_coo_tensor(
        torch.from_numpy(indices),
        torch.from_numpy(values),
        shape,
        is_coalesced=True,
        check_invariants=False,
    )
