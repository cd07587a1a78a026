"""A kernel asked for a buffer larger than memory raises MemoryError naming the buffer and
the bytes requested; the process lives on and the next call works."""

import pytest
import torch

from splat_scenes import camera, head_scene
from urhead.ops import rasterize_gaussians


def test_splat_image_too_large_for_memory_raises_memory_error():
    means, quats, scales, opacities, _, _ = head_scene(2, dtype=torch.float32)
    cam = camera(4096)
    # Two Gaussians with 2^20 colour channels: tiny inputs, but the (H, W, C) float32 image
    # they ask for is 4096² · 2^20 · 4 B = 64 TiB, which no allocator grants.
    channels = 1 << 20
    colors = torch.zeros(2, channels)
    requested_bytes = cam.height * cam.width * channels * 4
    with pytest.raises(MemoryError, match=rf"splat image \(H, W, C\).* {requested_bytes} bytes"):
        rasterize_gaussians(means, quats, scales, opacities, colors, cam)

    small = rasterize_gaussians(means, quats, scales, opacities, torch.ones(2, 3), camera(16))
    assert small.image.shape == (16, 16, 3)
    assert small.transmittance.min() < 1.0  # the Gaussians were drawn
