"""A new avatar for a subject: identity and per-frame FLAME parameters from the tracking,
maps initialised from the head and the first frames, Gaussians spread uniformly over UV."""

from __future__ import annotations

import math

import numpy as np
import torch

from urhead.errors import InvalidArgumentError
from urhead.head.mesh import vertex_normals
from urhead.head.model import HeadModel
from urhead.model.avatar import Avatar, flame_rows
from urhead.model.initial_maps import (
    initial_maps,
    project_colors,
    surface_area,
    texel_surface,
)
from urhead.model.map_layout import MapLayout
from urhead.model.sampling import UvSurface, set_gaussians
from urhead.ops import lbs


def frame_table(frames, num_expr: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(timesteps (T,), params (T, E + 18))`` from a split's tracked FLAME parameters."""
    params = flame_rows(frames.flame_params(), len(frames), num_expr)
    return torch.tensor(frames.timesteps, dtype=torch.int64), torch.from_numpy(params)


def build_avatar(
    head: HeadModel,
    train,
    *,
    resolution: int,
    sh_degree: int,
    gaussians: bool,
    initial_gaussians: int,
    offsets: bool = False,
    shading: bool = False,
    background: torch.Tensor,
    depth_eps: float,
    color_frames: int,
    rng: np.random.Generator,
) -> Avatar:
    """A fresh avatar for the training split ``train`` (a :class:`FrameSequence`).

    Args:
        resolution: side of the UV maps. sh_degree: 0–3. gaussians: with the Gaussian
        branch (O, S maps and Gaussians) or mesh only. initial_gaussians: how many, uniform
        over the UV area. offsets: with the Gaussians' own offset map E (zero at the
        start). shading: with the pose-driven shading maps A (zero at the start).
        color_frames: how many training frames (spread over the sequence) initialise C by
        projection; 0 starts from grey.
    """
    if not head.has_uv:
        raise InvalidArgumentError("the head model has no UV layout; an avatar needs one")
    if len(train) == 0:
        raise InvalidArgumentError("the subject has no training frames")
    flame = train.flame_params()
    num_expr = min(head.num_expr, flame["expr"].reshape(len(train), -1).shape[1])
    shape = torch.from_numpy(flame["shape"][0].reshape(-1)[: head.num_shape].astype(np.float32))
    static = None
    if "static_offset" in flame:
        offset = flame["static_offset"][0].reshape(-1, 3)
        if offset.shape[0] != head.num_vertices:
            raise InvalidArgumentError(
                f"static_offset has {offset.shape[0]} vertices, the head {head.num_vertices} "
                "(a VHAP export with teeth needs a head converted with teeth)"
            )
        static = torch.from_numpy(offset.astype(np.float32))
    timesteps, params = frame_table(train, num_expr)
    layout = MapLayout(sh_degree, gaussians, offsets, shading)
    avatar = Avatar(
        head=head,
        layout=layout,
        maps=torch.zeros(1, 1, layout.channels),
        gaussian_uv=torch.zeros(0, 2),
        gaussian_face=torch.zeros(0, dtype=torch.int64),
        gaussian_bary=torch.zeros(0, 3),
        shape=shape,
        static_offset=static,
        timesteps=timesteps,
        frame_params=params,
        background=background.float(),
        depth_eps=depth_eps,
    )
    tables = avatar.tables()
    faces = tables.faces
    rest = tables.lbs.v_template
    uv_raster = texel_surface(head, resolution)
    colors = None
    if color_frames > 0:
        picks = np.unique(np.linspace(0, len(train) - 1, color_frames).round().astype(int))
        frames = [train[int(i)] for i in picks]
        posed, normals = [], []
        with torch.no_grad():
            for i in picks:
                p = avatar.split_params(params[int(i)])
                out = lbs(p.expr[None], p.pose[None], transl=p.transl[None], **tables.lbs)
                posed.append(out.verts[0].contiguous())
                normals.append(vertex_normals(out.verts[0], faces))
        colors = project_colors(posed, frames, faces, uv_raster, normals)
    area = surface_area(rest, faces)
    # Half the mean spacing as the standard deviation: neighbours overlap without
    # blurring the mesh colour they start from.
    spacing = 0.5 * math.sqrt(area / max(initial_gaussians, 1))
    avatar.maps = initial_maps(layout, resolution, rest, faces, uv_raster, colors, spacing)
    if gaussians and initial_gaussians > 0:
        surface = UvSurface(head.uv_coords, head.uv_faces)
        set_gaussians(avatar, surface, surface.uniform(initial_gaussians, rng))
    return avatar
