"""Shared scenes and helpers of the splatting tests."""

from __future__ import annotations

import torch

import urhead


def camera(size: int = 64, width: int | None = None, principal=None) -> urhead.Camera:
    """A camera at the origin looking down +z (OpenCV axes), ~25° field of view."""
    width = size if width is None else width
    focal = 0.5 * size / 0.2217  # tan(12.5°)
    cx, cy = principal if principal is not None else (width / 2, size / 2)
    k = torch.tensor([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    return urhead.Camera(k, torch.eye(4), width, size)


def head_scene(n: int, dtype=torch.float64, seed: int = 0, scale=(-5.0, -3.5), size: int = 64):
    """n Gaussians of a few mm in a head-sized ellipsoid 0.75 m in front of the camera."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [0.05, 0.07, 0.06], dtype=torch.float64
    ) + torch.tensor([0.0, 0.0, 0.75], dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(*scale, generator=g))
    opacities = torch.empty(n, dtype=torch.float64).uniform_(0.1, 0.95, generator=g)
    sh = torch.randn(n, 16, 3, generator=g, dtype=torch.float64) * 0.3
    tensors = [t.to(dtype) for t in (means, quats, scales, opacities, sh)]
    return (*tensors, camera(size))


def requires_grad(*tensors):
    return [t.clone().requires_grad_(True) for t in tensors]


def weighted_loss(image, transmittance, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    w_img = torch.randn(image.shape, generator=g, dtype=torch.float64).to(image.dtype)
    w_t = torch.randn(transmittance.shape, generator=g, dtype=torch.float64).to(image.dtype)
    return (image * w_img).sum() + (transmittance * w_t).sum()
