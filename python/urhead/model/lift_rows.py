"""The Gaussians lifted straight from their map rows: one autograd node from the packed
``(N, channels)`` samples to positions, rotations, scales, opacities and colours.

Why one node: composed from :meth:`MapLayout.split`, ``exp``, ``sigmoid``,
:func:`~urhead.ops.lift_gaussians_geometry` and :func:`~urhead.ops.sh_shade`, the rows
reach four consumers. Each map column is copied out of the 56-wide rows on its own (a
strided pass over all of them each), the split's backward concatenates a zero-filled
colour gradient with the other maps', and autograd then adds the whole ``(N, channels)``
gradient of the SH colour to it. Here one kernel pass splits the maps after the colour out
of the rows (:func:`~urhead.ops.lift.lift_tail_split`) and one joins their gradients
(:func:`~urhead.ops.lift.lift_tail_grad`), and the colour's kernel writes the whole rows'
gradient, the other maps' columns in the same pass. The same kernels run on the same
values: the outputs are bit for bit the composed path's, and so are the gradients (up to
the sign of a zero colour gradient).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from urhead.model.map_layout import MapLayout, shading_features, shading_gain
from urhead.ops.lift import lift_backward, lift_forward, lift_tail_grad, lift_tail_split
from urhead.ops.shading import sh_shade_backward, sh_shade_forward


class GaussianLift(NamedTuple):
    """The Gaussians of one frame, lifted from their UV points."""

    means: torch.Tensor
    """(N, 3) world positions."""
    quats: torch.Tensor
    """(N, 4) rotations (w, x, y, z), local z along the posed normal."""
    scales: torch.Tensor
    """(N, 3) standard deviations, metres."""
    opacities: torch.Tensor
    """(N,) opacities in (0, 1)."""
    colors: torch.Tensor
    """(N, 3) colours seen from this frame's camera."""
    sh: torch.Tensor
    """(N, K, 3) SH coefficients, in the surface's rest frame."""
    frames: torch.Tensor
    """(N, 3, 3) skinning rotation at each Gaussian (rest frame → world), detached."""
    offset: torch.Tensor | None = None
    """(N,) each Gaussian's own offset E along the normal, metres (None without E)."""


class _Columns(NamedTuple):
    """Where each map sits among the columns after the colour (the rows' tail)."""

    colour: int
    """Channels of colour, the tail's start."""
    offset: int | None
    shading: slice | None

    @staticmethod
    def of(layout: MapLayout) -> _Columns:
        start = layout.normal.start
        shading = layout.shading_maps if layout.shading else None
        return _Columns(
            start,
            layout.offset - start if layout.offsets else None,
            None if shading is None else slice(shading.start - start, shading.stop - start),
        )


class _LiftRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rows, verts, rotations, face_verts, bary, centre, columns, degree):
        normals, lift, raw_scales, raw_opacities, offset = lift_tail_split(
            rows, columns.colour, columns.offset
        )
        saved = (verts, rotations, normals, lift, face_verts, bary, centre)
        means, _, quats, frames, view_dirs = lift_forward(*saved)
        scales = raw_scales.exp()
        opacities = torch.sigmoid(raw_opacities)
        rgb = sh_shade_forward(rows, view_dirs, degree)
        colors = rgb
        features = gain = None
        if columns.shading is not None:
            features = shading_features(frames)
            shading = columns.shading
            gain = shading_gain(
                rows[:, columns.colour + shading.start : columns.colour + shading.stop], features
            )
            colors = rgb * gain[:, None]
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(rows, *saved, view_dirs, scales, opacities, rgb, features, gain)
        ctx.columns, ctx.degree = columns, degree
        ctx.mark_non_differentiable(frames)
        outputs = (means, quats, scales, opacities, colors, frames)
        return (*outputs, offset) if offset is not None else outputs

    @staticmethod
    def backward(ctx, v_means, v_quats, v_scales, v_opacities, v_colors, _v_frames, *v_offset):
        rows, *saved, view_dirs, scales, opacities, rgb, features, gain = ctx.saved_tensors
        columns = ctx.columns
        need_rows, need_verts, need_rotations = ctx.needs_input_grad[:3]
        needs = (need_verts, need_rotations, need_rows, need_rows)
        v_verts = v_rotations = v_normals = v_lift = None
        if any(needs) and (v_means is not None or v_quats is not None):
            v_verts, v_rotations, v_normals, v_lift = lift_backward(
                saved, v_means, None, v_quats, needs
            )
        if not need_rows:
            return None, v_verts, v_rotations, None, None, None, None, None
        # The gradient of the columns after the colour (one pass: exp's and sigmoid's
        # derivatives as torch's), then the whole rows' in one pass.
        v_tail = lift_tail_grad(
            scales,
            opacities,
            rows.shape[1],
            columns.colour,
            columns.offset,
            v_normals if v_lift is not None else None,
            v_lift,
            v_scales,
            v_opacities,
            v_offset[0] if v_offset else None,
        )
        if v_colors is None:
            v_rows = rows.new_zeros(rows.shape)
            v_rows[:, columns.colour :] = v_tail
            return v_rows, v_verts, v_rotations, None, None, None, None, None
        v_rgb = v_colors
        if gain is not None:
            v_rgb = v_colors * gain[:, None]
            v_gain = (v_colors * rgb).sum(-1)[:, None]
            v_tail[:, columns.shading] = v_gain * features
        v_rows = sh_shade_backward(rows, view_dirs, ctx.degree, v_rgb, (v_tail, columns.colour))
        return v_rows, v_verts, v_rotations, None, None, None, None, None


def lift_rows(
    rows: torch.Tensor,
    layout: MapLayout,
    verts: torch.Tensor,
    rotations: torch.Tensor,
    face_verts: torch.Tensor,
    bary: torch.Tensor,
    centre: torch.Tensor,
    degree: int,
) -> GaussianLift:
    """The Gaussians of one frame from their map rows (``(N, layout.channels)``, float32 or
    float64, contiguous), as :meth:`Avatar.lift_gaussians` defines them: the geometry of
    :func:`~urhead.ops.lift_gaussians_geometry` from the normal N and the lift D (+ E),
    ``exp(S)``, ``sigmoid(O)``, and the SH colour of degree ``degree`` along the rest-frame
    view directions (scaled by ``1 + Σ A_ij (R − I)_ij`` with shading maps). ``face_verts``
    int32, ``bary`` and ``centre`` are constants of the verts' dtype."""
    if not layout.gaussians:
        raise ValueError("a mesh-only layout has no Gaussians to lift")
    if rows.ndim != 2 or rows.shape[1] != layout.channels:
        raise ValueError(f"rows must be (N, {layout.channels}), got {tuple(rows.shape)}")
    outputs = _LiftRows.apply(
        rows.contiguous(),
        verts.contiguous(),
        rotations.contiguous(),
        face_verts,
        bary,
        centre.to(verts.dtype).contiguous(),
        _Columns.of(layout),
        degree,
    )
    means, quats, scales, opacities, colors, frames, *offset = outputs
    return GaussianLift(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        sh=rows[:, layout.color].reshape(-1, layout.sh_coeffs, 3),
        frames=frames,
        offset=offset[0] if offset else None,
    )
