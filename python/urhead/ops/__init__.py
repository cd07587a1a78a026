"""Differentiable CPU kernels: each a private ``torch.autograd.Function`` over a Rust
forward/backward pair, with a documented public function; and the error-driven sampling's
per-frame bookkeeping (:mod:`urhead.ops.uv_error`, no gradients). Plain-torch references
for tests live in :mod:`urhead.ops._reference`."""

from urhead.ops.antialias import antialias, antialias_topology
from urhead.ops.composite import composite
from urhead.ops.interpolate import interpolate
from urhead.ops.lbs import LbsOutput, lbs
from urhead.ops.lift import LiftOutput, lift_gaussians_geometry
from urhead.ops.pixels import covered_pixels, scatter_pixels
from urhead.ops.rasterize import RasterOutput, UvRasterOutput, rasterize, rasterize_uv
from urhead.ops.rotate import rotate_normalize
from urhead.ops.sh_texture import ShadedTexels, half_maps, sh_texture
from urhead.ops.shading import sh_shade
from urhead.ops.splat import SplatOutput, normal_to_quat, rasterize_gaussians
from urhead.ops.ssim import masked_l1, masked_pixel_l1, masked_ssim, masked_ssim_l1
from urhead.ops.texture import TextureGather, texture
from urhead.ops.uv_error import accumulate_uv_error, nearest_covered_pixel

__all__ = [
    "LbsOutput",
    "LiftOutput",
    "RasterOutput",
    "ShadedTexels",
    "SplatOutput",
    "TextureGather",
    "UvRasterOutput",
    "accumulate_uv_error",
    "antialias",
    "antialias_topology",
    "composite",
    "covered_pixels",
    "half_maps",
    "interpolate",
    "lbs",
    "lift_gaussians_geometry",
    "masked_l1",
    "masked_pixel_l1",
    "masked_ssim",
    "masked_ssim_l1",
    "nearest_covered_pixel",
    "normal_to_quat",
    "rasterize",
    "rasterize_gaussians",
    "rasterize_uv",
    "rotate_normalize",
    "scatter_pixels",
    "sh_shade",
    "sh_texture",
    "texture",
]
