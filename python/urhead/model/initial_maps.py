"""Initial UV maps: N from the rest-pose normals of the subject's neutral head, C from the
first training frames projected onto the surface (the rest filled from what was seen),
D = 0, O and S constants chosen for the initial Gaussian density."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from urhead import hugepages
from urhead.head.mesh import vertex_normals
from urhead.model.map_layout import MapLayout
from urhead.ops import interpolate, rasterize, rasterize_uv
from urhead.sh import rgb_to_sh_dc

INITIAL_OPACITY = 0.1
"""Opacity of a fresh Gaussian (3DGS starts at 0.1): the mesh shows through at first."""

FLATNESS = 0.25
"""Initial ratio of a Gaussian's normal-axis scale to its tangent scales: surface discs."""

VISIBILITY_TOLERANCE = 3e-3
"""A texel counts as seen in a frame when it lies within this many metres of the mesh
depth at its pixel."""


def fill_holes(values: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Push-pull hole filling: texels with weight 0 take the weighted average of the
    nearest observed region at the coarsest scale that reaches them.

    Args:
        values: (R, R, C) map, meaningful where ``weight > 0``.
        weight: (R, R) non-negative confidence.
    Returns:
        (R, R, C) with holes filled (observed texels unchanged).
    """
    observed = weight > 0
    if bool(observed.all()) or not bool(observed.any()):
        return values
    v = (values * weight[..., None]).permute(2, 0, 1)[None]
    w = weight[None, None]
    h, wd = weight.shape
    if min(h, wd) < 2:
        mean = v.sum((2, 3)) / w.sum()
        return torch.where(observed[..., None], values, mean[0])
    coarse_v = F.avg_pool2d(v, 2, ceil_mode=True)
    coarse_w = F.avg_pool2d(w, 2, ceil_mode=True)
    coarse = coarse_v / coarse_w.clamp_min(1e-12)
    filled = fill_holes(coarse[0].permute(1, 2, 0), coarse_w[0, 0])
    up = F.interpolate(
        filled.permute(2, 0, 1)[None], size=(h, wd), mode="bilinear", align_corners=False
    )
    return torch.where(observed[..., None], values, up[0].permute(1, 2, 0))


def map_size(resolution) -> tuple[int, int]:
    """``(height, width)`` of maps given as a side (square) or as ``(height, width)``."""
    h, w = (resolution, resolution) if isinstance(resolution, int) else resolution
    return int(h), int(w)


def texel_surface(head, resolution):
    """The mesh point under each texel centre: ``(tri_id (H, W) int32, bary (H, W, 2))``
    from rasterizing the UV layout (DESIGN: UV faces list the geometry faces in order).
    ``resolution`` is the side of square maps or their ``(H, W)``."""
    uv = torch.tensor(head.uv_coords)
    uv_faces = torch.tensor(head.uv_faces)
    return rasterize_uv(uv, uv_faces, *map_size(resolution))


def project_colors(
    verts_per_frame: Sequence[torch.Tensor],
    frames: Sequence,
    faces: torch.Tensor,
    uv_raster,
    normals_per_frame: Sequence[torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Averages the frames' pixel colours over the texels that see them.

    Returns ``(rgb (H, W, 3), weight (H, W))``: per texel the mean colour over the frames
    where it is visible (front-facing, not occluded, inside the mask), weighted by the
    cosine of the viewing angle and the mask.
    """
    h, w = uv_raster.tri_id.shape
    covered = uv_raster.tri_id >= 0
    total = torch.zeros(h, w, 3)
    weight = torch.zeros(h, w)
    for verts, frame, vn in zip(verts_per_frame, frames, normals_per_frame, strict=True):
        cam = frame.camera
        points = interpolate(verts, uv_raster, faces)[covered]  # (M, 3)
        normal = interpolate(vn, uv_raster, faces)[covered]
        pix, depth = cam.project(points)
        raster = rasterize(verts.contiguous(), faces, cam)
        xi = pix[:, 0].floor().long().clamp(0, cam.width - 1)
        yi = pix[:, 1].floor().long().clamp(0, cam.height - 1)
        inside = (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0)
        inside &= pix[:, 1] < cam.height
        surface_depth = raster.depth[yi, xi]
        view = points - cam.center
        facing = -(normal * view).sum(-1) / view.norm(dim=-1).clamp_min(1e-12)
        visible = inside & (depth <= surface_depth + VISIBILITY_TOLERANCE) & (facing > 0.2)
        grid = torch.stack(
            [pix[:, 0] / cam.width * 2 - 1, pix[:, 1] / cam.height * 2 - 1], -1
        ).reshape(1, -1, 1, 2)
        image = torch.cat([frame.image, frame.mask[..., None]], -1).permute(2, 0, 1)[None]
        sampled = F.grid_sample(image, grid, align_corners=False)[0, :, :, 0].T  # (M, 4)
        w = torch.where(visible, facing * sampled[:, 3], torch.zeros_like(facing))
        total[covered] += sampled[:, :3] * w[:, None]
        weight[covered] += w
    rgb = total / weight.clamp_min(1e-12)[..., None]
    return rgb, weight


def initial_maps(
    layout: MapLayout,
    resolution,
    rest_verts: torch.Tensor,
    faces: torch.Tensor,
    uv_raster,
    colors: tuple[torch.Tensor, torch.Tensor] | None,
    gaussian_spacing: float,
) -> torch.Tensor:
    """(H, W, channels) float32 maps (``resolution`` a side or ``(H, W)``).

    Args:
        rest_verts: (V, 3) the subject's neutral head (identity applied, zero pose).
        uv_raster: :func:`texel_surface` at ``resolution``.
        colors: ``(rgb, weight)`` from :func:`project_colors`, or None for mid-grey.
        gaussian_spacing: typical distance between initial Gaussians, metres (S).
    """
    h, w = map_size(resolution)
    covered = uv_raster.tri_id >= 0
    maps = hugepages.zeros((h, w, layout.channels))
    rest_normals = vertex_normals(rest_verts, faces)
    normal_map = interpolate(rest_normals, uv_raster, faces)
    normal_map = fill_holes(normal_map, covered.float())
    maps[..., layout.normal] = normal_map / normal_map.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if colors is None:
        rgb = torch.full((h, w, 3), 0.5)
    else:
        rgb, weight = colors
        rgb = fill_holes(rgb, weight * covered)
    maps[..., 0:3] = rgb_to_sh_dc(rgb.clamp(0, 1))
    if layout.gaussians:
        maps[..., layout.opacity] = math.log(INITIAL_OPACITY / (1 - INITIAL_OPACITY))
        tangent = math.log(gaussian_spacing)
        maps[..., layout.scale] = torch.tensor(
            [tangent, tangent, tangent + math.log(FLATNESS)], dtype=torch.float32
        )
    return maps.contiguous()


def surface_area(verts: torch.Tensor, faces: torch.Tensor) -> float:
    f = faces.long()
    a, b, c = verts[f[:, 0]], verts[f[:, 1]], verts[f[:, 2]]
    return float(torch.linalg.cross(b - a, c - a).norm(dim=-1).sum() / 2)
