"""Standard 3D Gaussian Splatting PLY files (FORMATS.md "Exports"): binary little-endian,
one ``vertex`` element with float properties ``x y z nx ny nz f_dc_0..2 f_rest_0..44
opacity scale_0..2 rot_0..3`` — the set the reference 3DGS code and common viewers read.

``f_rest`` is channel-major as in 3DGS (all R coefficients 1..15, then G, then B), padded
with zeros to degree 3; opacity is a logit, scales are log standard deviations, ``rot`` a
(w, x, y, z) quaternion.
"""

from __future__ import annotations

from pathlib import Path

import torch

from urhead.errors import ShapeError

REST_PER_CHANNEL = 15
"""Degree-3 SH has 16 coefficients per colour channel, 15 beyond the DC term."""

PROPERTIES = (
    ["x", "y", "z", "nx", "ny", "nz"]
    + [f"f_dc_{i}" for i in range(3)]
    + [f"f_rest_{i}" for i in range(3 * REST_PER_CHANNEL)]
    + ["opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
)


def gaussian_ply_bytes(
    means: torch.Tensor,
    normals: torch.Tensor,
    sh: torch.Tensor,
    opacity_logits: torch.Tensor,
    log_scales: torch.Tensor,
    quats: torch.Tensor,
) -> bytes:
    """The PLY file of N Gaussians.

    Args:
        means: (N, 3) world positions. normals: (N, 3) (informative; viewers ignore them).
        sh: (N, K, 3) world-frame SH coefficients, K = (degree + 1)² ≤ 16.
        opacity_logits: (N,). log_scales: (N, 3). quats: (N, 4) (w, x, y, z).
    """
    n = means.shape[0]
    k = sh.shape[1] if sh.dim() == 3 else 0
    expected = {
        "means": (means, (n, 3)),
        "normals": (normals, (n, 3)),
        "opacity_logits": (opacity_logits, (n,)),
        "log_scales": (log_scales, (n, 3)),
        "quats": (quats, (n, 4)),
    }
    for name, (t, shape) in expected.items():
        if tuple(t.shape) != shape:
            raise ShapeError(f"{name} must be {shape}, got {tuple(t.shape)}")
    if sh.dim() != 3 or sh.shape[0] != n or sh.shape[2] != 3 or not 1 <= k <= 16:
        raise ShapeError(f"sh must be ({n}, K ≤ 16, 3), got {tuple(sh.shape)}")
    rest = torch.zeros(n, 3, REST_PER_CHANNEL, dtype=torch.float64)
    rest[:, :, : k - 1] = sh[:, 1:, :].double().transpose(1, 2)  # channel-major
    columns = [
        means.double(),
        normals.double(),
        sh[:, 0, :].double(),
        rest.reshape(n, -1),
        opacity_logits.double()[:, None],
        log_scales.double(),
        quats.double(),
    ]
    table = torch.cat(columns, 1).numpy().astype("<f4")
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
        + [f"property float {p}" for p in PROPERTIES]
        + ["end_header\n"]
    )
    return header.encode("ascii") + table.tobytes()


def write_gaussian_ply(path: Path, **arrays) -> None:
    """Writes :func:`gaussian_ply_bytes` to ``path`` (not atomically; callers write into
    a folder that is renamed into place)."""
    Path(path).write_bytes(gaussian_ply_bytes(**arrays))
