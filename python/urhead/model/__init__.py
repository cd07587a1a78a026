"""The URHead avatar: packed UV maps, UV-anchored Gaussians, per-frame FLAME parameters,
the joint mesh + Gaussian renderer, construction and the avatar directory."""

from urhead.model.avatar import Avatar, FlameParams, GaussianRender, MeshRender, Render
from urhead.model.build import build_avatar, frame_table
from urhead.model.io import load_avatar, save_avatar
from urhead.model.map_layout import MapLayout
from urhead.model.sampling import ErrorAccumulator, GaussianSampler, UvSurface, set_gaussians

__all__ = [
    "Avatar",
    "ErrorAccumulator",
    "FlameParams",
    "GaussianRender",
    "GaussianSampler",
    "MapLayout",
    "MeshRender",
    "Render",
    "UvSurface",
    "build_avatar",
    "frame_table",
    "load_avatar",
    "save_avatar",
    "set_gaussians",
]
