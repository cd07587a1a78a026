"""The avatar's two layers as world-space 3DGS arrays, for ``urhead export --ply``.

A standard 3DGS renderer composites Gaussians sorted by depth and has no mesh; the avatar
composites its Gaussian layer over an opaque textured mesh (Gaussians more than
``depth_eps`` behind the mesh are skipped). :func:`mesh_surfels` represents the mesh as
flat, opaque Gaussians ("surfels") tiling every triangle, so that file shows the whole
avatar:

- Sampling: each triangle of the displaced posed mesh is cut into n² similar
  sub-triangles, n = ⌈√area / spacing⌉, one surfel at each sub-triangle's centroid. The
  spacing is given in pixels of the frame's camera at the head's median depth.
- Shape: the covariance of the uniform distribution on the sub-triangle, ``Σ e·eᵀ / 36``
  over its edges, widened by ``SIGMA_GAIN`` so neighbours overlap without holes; the third
  axis (along the face normal) is ``THIN`` times the smaller in-plane one.
- Colour: the maps' SH coefficients at the surfel's UV point, rotated into the world frame
  like the Gaussians' (the mesh branch evaluates its colour in the same rest frame), so
  view-dependent colour is kept.
- Position: moved ``INSET`` spacings inward along the posed normal the Gaussians are
  lifted along. Gaussian tails and the renderer's 0.3 px² screen dilation grow a surfel
  silhouette by about a pixel at the default spacing; the inset (1 px there) cancels
  that, and places the surface behind the Gaussians that sit on it (their offsets are
  mostly within a millimetre of it), so depth sorting composites them over it as the
  avatar does.

The constants were chosen by measurement on a 512² fit (README "Export").
"""

from __future__ import annotations

import math
from functools import lru_cache

import torch

from urhead.camera import Camera
from urhead.model import Avatar
from urhead.model.avatar import FlameParams
from urhead.ops import texture
from urhead.sh import SH_C0
from urhead.use.sh_rotation import nearest_rotation, rotate_sh

DEFAULT_SPACING_PIXELS = 3.0
"""Surfel spacing at the frame's camera; see README "Export" for size against PSNR."""
SIGMA_GAIN = 1.2
"""In-plane standard deviations relative to the sub-triangle's own (uniform) ones."""
INSET = 1 / 3
"""Inward move of the surfels along the normal, in units of the spacing."""
THIN = 1e-2
"""Thickness of a surfel relative to its smaller in-plane standard deviation."""
SURFEL_OPACITY_LOGIT = math.log(0.999 / 0.001)
"""Opaque: the renderer clamps α at 0.99 at the centre anyway."""


def world_gaussians(avatar: Avatar, params: FlameParams, camera: Camera) -> dict:
    """The Gaussian layer of one frame as 3DGS file arrays: ``means`` (N, 3), ``normals``
    (N, 3), ``sh`` (N, K, 3) world-frame, ``opacity_logits`` (N,), ``log_scales`` (N, 3),
    ``quats`` (N, 4) (w, x, y, z)."""
    with torch.no_grad():
        verts, rotations = avatar.skin(params)
        lift = avatar.lift_gaussians(verts, rotations, camera)
        rows = avatar.lookup_fixed(avatar.gaussian_uv)  # the rows the lift used
        samples = avatar.layout.split(rows)
    return {
        "means": lift.means,
        "normals": _quat_z_axis(lift.quats),
        "sh": world_sh(avatar, rows, lift.frames),
        "opacity_logits": samples.opacity,
        "log_scales": samples.scale,
        "quats": lift.quats,
    }


def mesh_surfels(
    avatar: Avatar,
    params: FlameParams,
    camera: Camera,
    spacing_pixels: float = DEFAULT_SPACING_PIXELS,
) -> dict:
    """The mesh layer of one frame as flat opaque Gaussians (the arrays of
    :func:`world_gaussians`), ``spacing_pixels`` apart at ``camera``."""
    if not spacing_pixels > 0:
        raise ValueError(f"surfel spacing must be > 0 pixels, got {spacing_pixels}")
    tables = avatar.tables()
    with torch.no_grad():
        verts, rotations = avatar.skin(params)
        displaced, _ = avatar.displace(verts, rotations)
        metres_per_pixel = _metres_per_pixel(displaced, camera)
        faces = tables.faces_long
        corners = displaced.double()[faces]  # (F, 3, 3)
        area = 0.5 * _cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(
            dim=-1
        )
        cuts = (area.sqrt() / (spacing_pixels * metres_per_pixel)).ceil().clamp_min(1).long()
        face, bary = _subdivide(cuts)
        corner_ids = faces[face]
        weights = bary[:, :, None]
        centres = (corners[face] * weights).sum(1)
        frames = (rotations[corner_ids] * bary.float()[:, :, None, None]).sum(1)
        uv_corners = tables.uv_coords.double()[tables.uv_faces.long()[face]]
        uv = (uv_corners * weights).sum(1).float().contiguous()
        rows = texture(avatar.maps.detach(), uv)
        samples = avatar.layout.split(rows)
        inward = -_unit((frames * samples.normal[:, None, :]).sum(-1).double())
        means = centres + INSET * spacing_pixels * metres_per_pixel * inward
        edges = _edges(corners[face]) / cuts[face].double()[:, None, None]
        axes, log_scales = _triangle_gaussian(edges)
    return {
        "means": means.float(),
        "normals": axes[:, :, 2].float(),
        "sh": world_sh(avatar, rows, frames),
        "opacity_logits": torch.full((face.shape[0],), SURFEL_OPACITY_LOGIT),
        "log_scales": log_scales.float(),
        "quats": _matrix_to_quat(axes).float(),
    }


def world_sh(avatar: Avatar, rows: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """(P, K, 3) world-frame SH coefficients from map-sample rows (P, channels) whose colour
    the avatar evaluates in the rest frame of ``frames`` (P, 3, 3), the blended skinning
    rotations; with pose-driven shading maps, their gain (a positive per-sample factor on
    the colour) is folded into the coefficients."""
    layout = avatar.layout
    sh = rows[:, layout.color].reshape(-1, layout.sh_coeffs, 3).double()
    if layout.shading:
        features = (frames - torch.eye(3, dtype=frames.dtype)).reshape(-1, 9)
        gain = 1 + (rows[:, layout.shading_maps] * features).sum(-1).double()
        # gain·(B·c + ½) = B·(gain·c) + ½ + (gain − 1)·½ with the last term in the DC band.
        sh = sh * gain[:, None, None]
        sh[:, 0, :] += ((gain - 1) * 0.5 / SH_C0)[:, None]
    return rotate_sh(sh, nearest_rotation(frames)).float()


@lru_cache(maxsize=64)
def _centroid_barycentrics(n: int) -> torch.Tensor:
    """(n², 3) float64 barycentrics of the centroids of the n² sub-triangles a triangle is
    cut into by n equal steps along each edge (n(n+1)/2 upright, n(n−1)/2 inverted)."""
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    upright = i + j <= n - 1
    inverted = i + j <= n - 2
    a = torch.cat([i[upright] + 1 / 3, i[inverted] + 2 / 3]).double() / n
    b = torch.cat([j[upright] + 1 / 3, j[inverted] + 2 / 3]).double() / n
    return torch.stack([a, b, 1 - a - b], 1)


def _subdivide(cuts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(face (M,), bary (M, 3))``: every face f cut ``cuts[f]`` times per edge."""
    faces, barys = [], []
    for n in cuts.unique().tolist():
        selected = (cuts == n).nonzero()[:, 0]
        pattern = _centroid_barycentrics(n)
        faces.append(selected.repeat_interleave(pattern.shape[0]))
        barys.append(pattern.repeat(selected.shape[0], 1))
    return torch.cat(faces), torch.cat(barys)


def _triangle_gaussian(edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """From (M, 3, 3) edge vectors of triangles: ``(axes (M, 3, 3), log_scales (M, 3))``,
    a proper rotation whose columns are the in-plane principal axes (larger first) and the
    normal, and the log standard deviations along them (``SIGMA_GAIN`` times the uniform
    distribution's in the plane, ``THIN`` times the smaller across)."""
    covariance = (edges[:, :, :, None] * edges[:, :, None, :]).sum(1) / 36
    variances, vectors = torch.linalg.eigh(covariance)  # ascending: the normal first
    axes = vectors.flip(-1)
    axes[:, :, 2] *= torch.linalg.det(axes).sign()[:, None]
    sigma = SIGMA_GAIN * variances[:, 1:].flip(-1).clamp_min(1e-24).sqrt()
    scales = torch.cat([sigma, THIN * sigma[:, 1:]], 1)
    return axes, scales.log()


def _matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """(M, 3, 3) proper rotations → (M, 4) unit quaternions (w, x, y, z), each from the
    best-conditioned of the four standard forms (the one with the largest 4q_i²)."""
    d0, d1, d2 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    a = m[:, 2, 1] - m[:, 1, 2]  # 4wx
    b = m[:, 0, 2] - m[:, 2, 0]  # 4wy
    c = m[:, 1, 0] - m[:, 0, 1]  # 4wz
    xy = m[:, 0, 1] + m[:, 1, 0]  # 4xy
    xz = m[:, 0, 2] + m[:, 2, 0]  # 4xz
    yz = m[:, 1, 2] + m[:, 2, 1]  # 4yz
    forms = torch.stack(
        [
            torch.stack([1 + d0 + d1 + d2, a, b, c], -1),  # 4w·q
            torch.stack([a, 1 + d0 - d1 - d2, xy, xz], -1),  # 4x·q
            torch.stack([b, xy, 1 - d0 + d1 - d2, yz], -1),  # 4y·q
            torch.stack([c, xz, yz, 1 - d0 - d1 + d2], -1),  # 4z·q
        ],
        1,
    )
    best = forms.diagonal(dim1=1, dim2=2).argmax(1)
    q = forms[torch.arange(m.shape[0]), best]
    return q / q.norm(dim=-1, keepdim=True)


def _metres_per_pixel(verts: torch.Tensor, camera: Camera) -> float:
    """The size of one pixel at the median view depth of ``verts`` (V, 3)."""
    view = verts.double() @ camera.viewmat[:3, :3].double().T + camera.viewmat[:3, 3].double()
    return float(view[:, 2].median()) / float(camera.K[0, 0])


def _edges(corners: torch.Tensor) -> torch.Tensor:
    return torch.stack(
        [
            corners[:, 1] - corners[:, 0],
            corners[:, 2] - corners[:, 1],
            corners[:, 0] - corners[:, 2],
        ],
        1,
    )


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-1)


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-30)


def _quat_z_axis(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) unit (w, x, y, z) → (N, 3) the rotated z axis (the surface normal here)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)
