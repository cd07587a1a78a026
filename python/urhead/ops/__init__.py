"""Differentiable CPU kernels: each a private ``torch.autograd.Function`` over a Rust
forward/backward pair, with a documented public function. Plain-torch references for
tests live in :mod:`urhead.ops._reference`."""

from urhead.ops.lbs import LbsOutput, lbs
from urhead.ops.splat import SplatOutput, normal_to_quat, rasterize_gaussians

__all__ = ["LbsOutput", "SplatOutput", "lbs", "normal_to_quat", "rasterize_gaussians"]
