"""Differentiable CPU kernels: each a private ``torch.autograd.Function`` over a Rust
forward/backward pair, with a documented public function. Plain-torch references for
tests live in :mod:`urhead.ops._reference`."""

from urhead.ops.lbs import LbsOutput, lbs

__all__ = ["LbsOutput", "lbs"]
