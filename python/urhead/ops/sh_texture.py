"""A texture lookup shaded with spherical harmonics in one pass, Rust forward and adjoint:
the mesh branch's colour (and normal) at its covered pixels, whose backward never reads the
maps again (the forward keeps each output's UV derivatives while the texels are in cache)."""

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
    native,
    to_numpy,
)
from urhead.ops.texture import TextureGather, texture_gradient


class ShadedTexels(NamedTuple):
    rgb: torch.Tensor
    """(P, 3) ``max(Σ_k b_k(dir)·c_k + 0.5, 0)`` per colour."""
    extra: torch.Tensor
    """(P, E) the ``extra`` channels as they are."""


class _ShTexture(torch.autograd.Function):
    @staticmethod
    def forward(ctx, tex, uv, dirs, degree, extra, gather):
        source = tex.detach() if gather is None else gather.tex
        dtype = uv.dtype  # the texture's, or float32 for a float16 texture
        wants_grad = ctx.needs_input_grad[0] or ctx.needs_input_grad[1]
        rgb, extra_values, raw_rgb, slopes = native("sh_texture_forward")(
            to_numpy("tex", source, source.dtype),
            to_numpy("uv", uv, dtype),
            to_numpy("dirs", dirs, dtype),
            degree,
            extra,
            (wants_grad, ctx.needs_input_grad[1]),
            num_threads(),
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(uv, dirs, from_numpy(raw_rgb), from_numpy(slopes))
        ctx.degree, ctx.extra, ctx.gather = degree, extra, gather
        ctx.tex = source  # read only by a gradient to the texture without a gather
        return torch.from_numpy(rgb), torch.from_numpy(extra_values)

    @staticmethod
    def backward(ctx, v_rgb, v_extra):
        need_tex, need_uv = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if (v_rgb is None and v_extra is None) or not (need_tex or need_uv):
            return None, None, None, None, None, None
        uv, dirs, raw_rgb, slopes = ctx.saved_tensors
        tex = ctx.tex
        v_rows, v_uv = native("sh_texture_backward")(
            uv.numpy(),
            dirs.numpy(),
            ctx.degree,
            tex.shape[-1],
            ctx.extra,
            raw_rgb.numpy(),
            None if slopes is None else slopes.numpy(),
            grad_to_numpy("v_rgb", v_rgb, uv.dtype),
            grad_to_numpy("v_extra", v_extra, uv.dtype),
            need_tex,
            num_threads(),
        )
        v_tex = None
        if need_tex:
            if ctx.gather is not None:
                ctx.gather.record(uv.detach(), torch.from_numpy(v_rows))
            else:
                v_tex = texture_gradient(tex, uv, v_rows)
        return v_tex, from_numpy(v_uv), None, None, None, None


def sh_texture(
    tex: torch.Tensor,
    uv: torch.Tensor,
    dirs: torch.Tensor,
    degree: int,
    extra: slice | None = None,
    *,
    gather: TextureGather | None = None,
) -> ShadedTexels:
    """SH colour of bilinear texture samples along view directions, and some channels as
    they are: the same values as ``texture(tex, uv)`` followed by
    :func:`~urhead.ops.sh_shade` on the rows and a slice of them, bit for bit.

    Args:
        tex: (Ht, Wt, C) texture whose first 3·(degree + 1)² channels are SH coefficients,
            coefficient-major (as :func:`~urhead.ops.sh_shade` reads them), float32 or
            float64, contiguous; usually a parameter. Or a float16 copy of one that is
            frozen (no gradient, no ``gather``), read in float32 — half the bytes for a
            rendered avatar's maps, values those of its float32 widening exactly
            (:func:`half_maps` makes such a copy).
        uv: (P, 2) texture coordinates, the :func:`~urhead.ops.texture` convention, of
            ``tex``'s dtype (float32 for a float16 ``tex``).
        dirs: (P, 3) unit view directions; constants (no gradient flows to them), finite.
        degree: 0–3.
        extra: channels after the colour to return as they are (e.g. the normal map), or
            None.
        gather: a :class:`~urhead.ops.TextureGather` of ``tex``: the texture's gradient is
            recorded there (as for :meth:`TextureGather.sample`) instead of flowing back.

    Returns:
        :class:`ShadedTexels` ``(rgb (P, 3), extra (P, E))``: ``max(Σ_k b_k(dir)·c_k + 0.5,
        0)`` per colour, and the E ``extra`` channels — two arrays, not slices of one, so
        each part's gradient arrives alone (a slice's backward would fill a zero (P, 3 + E)
        array for each part and add them: ~2 ms of a training step).

    Gradients: to ``uv`` (from UV derivatives the forward keeps, so the backward reads no
    texel; equal to the lookup's up to rounding) and to ``tex`` (a coalesced sparse COO
    tensor as :func:`~urhead.ops.texture` gives, or recorded in ``gather``). A colour
    channel clamped at 0 passes no gradient; a sample with a non-finite coordinate reads
    zeros (colour 0.5) and passes none to ``uv``. Every sample is independent: the same bits
    for any thread count. Threads: ``URHEAD_NUM_THREADS`` or ``torch.get_num_threads()``.
    """
    if isinstance(tex, torch.Tensor) and tex.dtype == torch.float16:
        check_tensor("tex", tex)
        if tex.requires_grad or gather is not None:
            raise InvalidArgumentError(
                "a float16 tex is read-only: it must not require grad nor have a gather "
                "(train on the float32 maps)"
            )
        dtype = torch.float32
    else:
        dtype = float_dtype("tex", tex)
    check_shape("tex", tex, 3, None, "(Ht, Wt, C)")
    for name, t, width in (("uv", uv, 2), ("dirs", dirs, 3)):
        if t.dtype != dtype:
            raise DTypeError(
                f"{name} must be {dtype} (tex's dtype; float32 for float16 tex), got {t.dtype}"
            )
        check_shape(name, t, 2, width, f"(P, {width})")
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= 3:
        raise InvalidArgumentError(f"degree must be an int in [0, 3], got {degree!r}")
    if extra is None:
        extra = slice(0, 0)
    if extra.step not in (None, 1) or extra.start is None or extra.stop is None:
        raise InvalidArgumentError(f"extra must be a slice start:stop of channels, got {extra}")
    if gather is not None and gather.source is not tex:
        raise InvalidArgumentError("gather must be a TextureGather of tex")
    return ShadedTexels(
        *_ShTexture.apply(
            tex,
            uv.contiguous(),
            dirs.detach().contiguous(),
            degree,
            (int(extra.start), int(extra.stop)),
            gather,
        )
    )


HALF_MAX = 65504.0
"""The largest finite float16."""


def half_maps(tex: torch.Tensor, channels: int | None = None) -> torch.Tensor | None:
    """A float16 copy of a frozen float32 texture for :func:`sh_texture` to read (half the
    bytes: a rendered avatar's lookups are bound by the cache lines they read), or None
    when a value is non-finite or beyond float16's range (±65504): the caller keeps
    reading ``tex``. Values keep 2⁻¹¹ relative precision (round to nearest); those below
    float16's smallest normal (6.1e-5) keep an absolute one of 3e-8 (NUMERICS.md case 34).

    Args:
        tex: (Ht, Wt, C) float32, contiguous.
        channels: copy the first ``channels`` only (default all): a prefix keeps every
            channel index the same, so the copy serves any lookup of those channels with
            fewer bytes a texel (the colour alone, without the maps only vertices and
            Gaussians read: at the paper's 56 channels a 512² frame's lookups
            5.74 → 5.37 ms for 48). Values past them are not checked.

    Returns:
        (Ht, Wt, channels or C) float16, or None."""
    check_tensor("tex", tex)
    if tex.dtype != torch.float32:
        raise DTypeError(f"tex must be float32, got {tex.dtype}")
    if tex.ndim != 3:
        raise ShapeError(f"tex must be (Ht, Wt, C), got shape {tuple(tex.shape)}")
    total = tex.shape[-1]
    if channels is None:
        channels = total
    if isinstance(channels, bool) or not isinstance(channels, int) or not 1 <= channels <= total:
        raise InvalidArgumentError(f"channels must be an int in [1, {total}], got {channels!r}")
    detached = tex.detach()[..., :channels]
    if detached.numel():
        low, high = torch.aminmax(detached)  # no |tex| temporary the size of the maps
        if not bool((low >= -HALF_MAX) & (high <= HALF_MAX)):  # False for NaN too
            return None
    from urhead import hugepages  # here: hugepages imports the ops' bridge

    # On huge pages, as the maps: the pixels' reads are random, and on 4 KiB pages most
    # of them would miss the TLB.
    half = hugepages.zeros(detached.shape, torch.float16)
    half.copy_(detached)  # rounded to nearest, as .to(torch.float16)
    return half
