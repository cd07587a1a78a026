"""Real spherical harmonics in the 3D Gaussian Splatting convention (constants and signs),
in plain torch: the kernels' references, the initial colour map, the export and its SH
rotation. The renderers evaluate SH in Rust (``urhead_core::sh``, through
:func:`urhead.ops.sh_shade` and the splatting kernels).

A colour is ``max(Σ_k basis_k(dir)·coeff_k + 0.5, 0)`` with ``dir`` the unit direction from
the camera centre to the surface point; coefficients are (..., K, 3) with K = (degree + 1)².
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, 3) unit directions → (N, (degree+1)²) real SH basis (3DGS constants and signs)."""
    x, y, z = dirs.unbind(-1)
    b = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        b += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        b += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(b, -1)


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """The degree-0 coefficient that renders ``rgb`` (any shape) from every direction."""
    return (rgb - 0.5) / SH_C0
