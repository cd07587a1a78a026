"""The training objective of the paper (Eq. 8–11):

L = λ_ssim (1 − SSIM(I, I_gt)) + (1 − λ_ssim) L_photo + λ_n L_normal + λ_L L_lap,
L_photo = (1 − w) ‖I − I_gt‖₁ + w ‖I_mesh − I_gt‖₁, w = 0.2 (the mesh term).

Terms whose data or branch is absent are not computed at all: no normal maps → no
L_normal; mesh-only fit → I is I_mesh and L_photo is one L1; λ = 0 → skipped.

Region: the photometric terms cover the whole matted image (the background is known, and
pixels outside the mask are what stops the silhouette from growing); metrics are taken
inside the head mask. L_lap regularises the displacement field: it is the paper's
Laplacian applied to the per-vertex offsets v̂ − v, so the FLAME surface's own curvature is
not penalised and only D is smoothed (our reading of "suppress noisy displacements").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch

from urhead.head.mesh import uniform_laplacian
from urhead.losses import l1, pixel_l1, ssim_l1
from urhead.model.avatar import Render

OFFSET_UNIT = 0.1
"""metres: the Gaussian offset regulariser is the mean of (E / OFFSET_UNIT)²."""


@dataclass(frozen=True, eq=False)
class Objective:
    """The training objective of one fit (module docstring): its weights, and the mesh's
    uniform Laplacian (V, V) for L_lap, built once. Call it on a rendered training frame."""

    lambda_ssim: float
    mesh_term: float
    lambda_normal: float
    lambda_laplacian: float
    laplacian: sp.csr_matrix
    use_normals: bool
    lambda_offset: float = 0.0
    lambda_alpha: float = 0.0

    @classmethod
    def for_fit(cls, config, head, use_normals: bool) -> Objective:
        """The objective a :class:`~urhead.config.FitConfig` asks for, on ``head``'s mesh."""
        return cls(
            lambda_ssim=config.lambda_ssim,
            mesh_term=config.mesh_term,
            lambda_normal=config.lambda_normal,
            lambda_laplacian=config.lambda_laplacian,
            laplacian=uniform_laplacian(torch.tensor(head.faces), head.num_vertices),
            use_normals=use_normals,
            lambda_offset=config.lambda_offset,
            lambda_alpha=config.lambda_alpha,
        )

    def __call__(self, render: Render, frame) -> torch.Tensor:
        """The loss (a scalar) of one rendered training frame (a dataset :class:`Frame`)."""
        target = frame.image
        image = render.image
        # (1 − λ)·photo + λ·(1 − SSIM), each term weighted inside its kernel, so the summed
        # loss hands every kernel's gradient back unscaled (no pass over an image to scale it).
        photo_weight = 1 - self.lambda_ssim
        with_mesh_term = render.gaussians is not None and self.mesh_term > 0
        image_weight = photo_weight * (1 - self.mesh_term) if with_mesh_term else photo_weight
        if self.lambda_ssim > 0:  # the image's L1 and SSIM in one kernel pass
            total = ssim_l1(image, target, ssim_weight=-self.lambda_ssim, l1_weight=image_weight)
            total = total + self.lambda_ssim
        else:
            total = l1(image, target, weight=image_weight)
        if with_mesh_term:  # the mesh's colour read in place from its RGBA
            total = total + l1(render.mesh.rgba, target, weight=photo_weight * self.mesh_term)
        if self.use_normals and self.lambda_normal > 0:
            total = total + normal_loss(render, frame, weight=self.lambda_normal)
        if self.lambda_laplacian > 0:
            lap = laplacian_loss(render.mesh.offsets, self.laplacian)
            total = total + self.lambda_laplacian * lap
        if self.lambda_alpha > 0:
            sil = silhouette_loss(render, frame)
            total = total + self.lambda_alpha * sil
        offset = render.gaussians.lift.offset if render.gaussians is not None else None
        if offset is not None and self.lambda_offset > 0 and offset.numel():
            # In units of (100 mm)²: a hair shell of ~1 cm costs 1 % of λ per Gaussian.
            reg = (offset / OFFSET_UNIT).square().mean()
            total = total + self.lambda_offset * reg
        return total


def coverage(render: Render) -> torch.Tensor:
    """(H, W) opacity of the composite: Gaussians over the mesh, 1 − T·(1 − α_mesh)."""
    if render.gaussians is None:
        return render.mesh.alpha
    return 1 - render.gaussians.transmittance * (1 - render.mesh.alpha)


def silhouette_loss(render: Render, frame) -> torch.Tensor:
    """Mean |coverage − mask| over the image: the matte's own antialiased edge is the
    target, so the silhouette is fitted directly rather than only through colour."""
    return (coverage(render) - frame.mask).abs().mean()


def normal_loss(render: Render, frame, weight: float = 1.0) -> torch.Tensor:
    """Mean ‖N_mesh − N_gt‖₁ over covered pixels inside the mask where N_gt is defined
    (camera axes, both unit), times ``weight`` (inside the kernel, as the photometric
    terms')."""
    mesh = render.mesh
    return pixel_l1(mesh.normals, mesh.pixels, frame.normals, frame.mask, weight=weight)


def laplacian_loss(verts: torch.Tensor, laplacian: sp.csr_matrix) -> torch.Tensor:
    """(1/V) Σ_i ‖δ_i‖², δ = L·v, for (V, 3) or (B, V, 3) vertices and the (V, V) operator
    of :func:`~urhead.head.mesh.uniform_laplacian` (the paper's L_lap)."""
    return _SquaredLaplacian.apply(verts, laplacian)


class _SquaredLaplacian(torch.autograd.Function):
    """mean_i ‖(L·v)_i‖² and its gradient (2 / (B·V))·Lᵀ·(L·v), with scipy's CSR products
    (torch's sparse product and its backward cost ~2 ms a step here, these ~0.1 ms)."""

    @staticmethod
    def forward(ctx, verts, laplacian):
        flat = verts.detach().reshape(-1, verts.shape[-2], 3).numpy()
        dtype = flat.dtype
        deltas = np.stack([(laplacian @ v).astype(dtype, copy=False) for v in flat])
        ctx.save_for_backward(torch.from_numpy(deltas))
        ctx.laplacian, ctx.shape = laplacian, verts.shape
        return torch.tensor(
            float(np.square(deltas, dtype=np.float64).sum(-1).mean()), dtype=verts.dtype
        )

    @staticmethod
    def backward(ctx, grad):
        (deltas,) = ctx.saved_tensors
        d = deltas.numpy()
        scale = 2 * float(grad) / (d.shape[0] * d.shape[1])
        v_verts = np.stack([(ctx.laplacian.T @ (scale * x)).astype(d.dtype, copy=False) for x in d])
        return torch.from_numpy(v_verts).reshape(ctx.shape), None
