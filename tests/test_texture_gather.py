"""TextureGather: several lookups, one coalesced texture gradient, identical to what separate
texture() calls give through autograd; UV gradients unchanged."""

from __future__ import annotations

import pytest
import torch

from urhead.ops import TextureGather, texture


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gathered_gradient_equals_autograd_sum(dtype):
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(13, 17, 5, generator=g, dtype=dtype)
    uvs = [torch.rand(n, 2, generator=g, dtype=dtype) * 1.2 - 0.1 for n in (40, 7, 25)]
    uvs[1][3] = float("nan")  # a non-finite UV contributes nothing, as in texture()
    weights = [torch.randn(u.shape[0], 5, generator=g, dtype=dtype) for u in uvs]

    leaf = tex.clone().requires_grad_(True)
    ref_uv = [u.clone().requires_grad_(True) for u in uvs]
    sum(((texture(leaf, u) * w).sum() for u, w in zip(ref_uv, weights, strict=True))).backward()

    gather = TextureGather(tex.clone().requires_grad_(True))
    got_uv = [u.clone().requires_grad_(True) for u in uvs]
    samples = [gather.sample(u) for u in got_uv]
    for s, u in zip(samples, uvs, strict=True):
        assert torch.equal(s, texture(tex, u))
    sum(((s * w).sum() for s, w in zip(samples, weights, strict=True))).backward()
    grad = gather.gradient()
    assert grad.is_coalesced()
    assert torch.allclose(
        grad.to_dense(),
        leaf.grad.to_dense(),
        rtol=0,
        atol=1e-12 if dtype == torch.float64 else 1e-5,
    )
    for a, b in zip(got_uv, ref_uv, strict=True):
        assert torch.allclose(a.grad, b.grad, equal_nan=True)
    assert gather.gradient() is None  # cleared


def test_texels_outside_lookups_are_absent():
    tex = torch.zeros(64, 64, 2, requires_grad=True)
    gather = TextureGather(tex)
    uv = torch.tensor([[0.25, 0.25], [0.26, 0.25]])
    gather.sample(uv).sum().backward()
    rows = gather.gradient().indices()
    assert tex.grad is None
    assert rows.shape[1] <= 8  # at most 4 texels per lookup
    assert int(rows[0].min()) >= 64 * 3 // 4 - 2 and int(rows[1].max()) <= 64 // 4 + 2


def test_accumulating_gather_fills_the_source_grad_once_per_backward():
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(9, 11, 3, generator=g)
    uvs = [torch.rand(n, 2, generator=g) for n in (30, 12)]
    weights = [torch.randn(u.shape[0], 3, generator=g) for u in uvs]

    explicit = TextureGather(tex.clone().requires_grad_(True))
    sum((explicit.sample(u) * w).sum() for u, w in zip(uvs, weights, strict=True)).backward()
    expected = explicit.gradient()

    leaf = tex.clone().requires_grad_(True)
    gather = TextureGather(leaf, accumulate=True)
    sum((gather.sample(u) * w).sum() for u, w in zip(uvs, weights, strict=True)).backward()
    assert leaf.grad.is_sparse and leaf.grad.is_coalesced()
    assert torch.equal(leaf.grad.indices(), expected.indices())
    assert torch.equal(leaf.grad.values(), expected.values())
    assert gather.gradient() is None  # consumed by the backward pass

    (gather.sample(uvs[0]) * weights[0]).sum().backward()  # a second pass adds to it
    alone = TextureGather(tex.clone().requires_grad_(True))
    (alone.sample(uvs[0]) * weights[0]).sum().backward()
    assert torch.allclose(
        leaf.grad.to_dense(), expected.to_dense() + alone.gradient().to_dense(), atol=1e-6
    )


def test_samples_are_the_recorded_lookups_never_joined():
    """One ``(uv, v_out)`` segment a lookup (in the order the backward pass reached them),
    an empty lookup included: the lookup's own UVs, not a copy, and its output gradient."""
    tex = torch.rand(9, 11, 3, requires_grad=True)
    gather = TextureGather(tex)
    uvs = [torch.rand(n, 2) for n in (30, 0, 12)]
    outs = [gather.sample(u) for u in uvs]
    weights = [torch.randn(u.shape[0], 3) for u in uvs]
    sum((o * w).sum() for o, w in zip(outs, weights, strict=True)).backward()
    segments = {len(uv): (uv, v_out) for uv, v_out in gather.samples()}
    assert sorted(segments) == [0, 12, 30]
    for u, w in zip(uvs, weights, strict=True):
        uv, v_out = segments[len(u)]
        assert torch.equal(uv, u) and torch.equal(v_out, w)
        assert uv.is_contiguous() and v_out.is_contiguous()
        assert len(u) == 0 or uv.data_ptr() == u.data_ptr()
    assert gather.samples() is None  # cleared
