"""Rotating real spherical-harmonics coefficients (3DGS basis, degrees 0–3).

The avatar evaluates a Gaussian's SH colour with the view direction in its surface's rest
frame, ``colour(d) = B(Qᵀd)·c``; a standard 3DGS file evaluates ``B(d)·c'`` with the
world direction. Each band l of the basis is closed under rotation, so there is a
(2l+1)² matrix M_l(Q) with ``B_l(Qᵀd) = B_l(d)·M_l`` for every d, and ``c'_l = M_l·c_l``.
M_l is found exactly by evaluating both sides at a fixed set of well-spread directions
(more than 2l+1, so the fixed matrix B_l(dᵢ) has full column rank) and solving the linear
system with its precomputed pseudo-inverse, batched over the Gaussians in float64.
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

from urhead.errors import ShapeError
from urhead.sh import sh_basis

_PROBES = 32
"""Directions the bands are matched at (≥ 7 for degree 3; more improves conditioning)."""


@lru_cache(maxsize=1)
def _probe_directions() -> torch.Tensor:
    """(P, 3) float64 unit directions on a Fibonacci spiral."""
    i = torch.arange(_PROBES, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / _PROBES
    phi = i * math.pi * (3 - math.sqrt(5))
    r = (1 - z * z).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], -1)


@lru_cache(maxsize=4)
def _band_pinv(degree: int) -> tuple[torch.Tensor, ...]:
    """Per band l ≥ 1: pinv of B_l at the probes, (2l+1, P) float64."""
    basis = sh_basis(_probe_directions(), degree)
    return tuple(
        torch.linalg.pinv(basis[:, band * band : (band + 1) ** 2]) for band in range(1, degree + 1)
    )


def nearest_rotation(matrices: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) → the nearest proper rotations (polar factor U·Vᵀ of the SVD, det +1)."""
    u, _, vh = torch.linalg.svd(matrices.double())
    det = torch.linalg.det(u @ vh)
    fix = torch.ones_like(u[:, 0])
    fix[:, 2] = det.sign()
    return (u * fix[:, None, :]) @ vh


def rotate_sh(coeffs: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """World-frame coefficients of SH colours defined in rotated frames.

    Args:
        coeffs: (N, K, 3) coefficients with K = (degree + 1)², degree ≤ 3, evaluated in the
            local frame: ``colour(d) = B(Qᵀd)·coeffs``.
        rotations: (N, 3, 3) proper rotations Q (local → world).

    Returns:
        (N, K, 3) coefficients c' with ``B(d)·c' = B(Qᵀd)·coeffs`` for every unit d, in the
        dtype of ``coeffs``. Degree 0 is unchanged.
    """
    if coeffs.dim() != 3 or coeffs.shape[2] != 3:
        raise ShapeError(f"coeffs must be (N, K, 3), got {tuple(coeffs.shape)}")
    n, k = coeffs.shape[:2]
    degree = math.isqrt(k) - 1
    if (degree + 1) ** 2 != k or degree > 3:
        raise ShapeError(f"coeffs must have K = (degree + 1)² ≤ 16 coefficients, got {k}")
    if tuple(rotations.shape) != (n, 3, 3):
        raise ShapeError(f"rotations must be ({n}, 3, 3), got {tuple(rotations.shape)}")
    if degree == 0:
        return coeffs.clone()
    probes = _probe_directions()
    local = torch.einsum("pi,nij->npj", probes, rotations.double())  # rows Qᵀd
    rotated = sh_basis(local.reshape(-1, 3), degree).reshape(n, _PROBES, k)
    c = coeffs.double()
    out = [c[:, :1]]
    for degree_l, pinv in enumerate(_band_pinv(degree), start=1):
        band = slice(degree_l**2, (degree_l + 1) ** 2)
        m = pinv @ rotated[:, :, band]  # (N, 2l+1, 2l+1): B_l(Qᵀd) = B_l(d)·M
        out.append(m @ c[:, band])
    return torch.cat(out, 1).to(coeffs.dtype)
