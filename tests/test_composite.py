"""composite: the kernel against its plain-torch reference (float64 values and every
gradient), finite differences, a back image wider than its colour, non-finite values,
threads, bad input, and the avatar's render against the torch expression it replaces."""

from __future__ import annotations

import pytest
import torch

from test_model import camera, make_avatar
from urhead.errors import DTypeError, ShapeError
from urhead.head import procedural_head
from urhead.ops import _reference, composite

F64 = torch.float64


def _case(h=7, w=5, s=4, dtype=F64, seed=0):
    g = torch.Generator().manual_seed(seed)
    front = torch.rand(h, w, 3, generator=g, dtype=F64)
    transmittance = torch.rand(h, w, generator=g, dtype=F64)
    back = torch.rand(h, w, s, generator=g, dtype=F64)
    return front.to(dtype), transmittance.to(dtype), back.to(dtype)


def _run(fn, inputs, weights):
    leaves = [x.clone().requires_grad_(True) for x in inputs]
    out = fn(*leaves)
    (out * weights).sum().backward()
    return [out.detach()] + [x.grad for x in leaves]


@pytest.mark.parametrize("channels", [3, 4, 6])
def test_matches_reference_float64(channels):
    inputs = _case(s=channels)
    weights = torch.randn(7, 5, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    ours, ref = _run(composite, inputs, weights), _run(_reference.composite, inputs, weights)
    for a, b in zip(ours, ref, strict=True):
        assert a.shape == b.shape and torch.allclose(a, b, rtol=1e-15, atol=1e-15)
    assert ours[3][..., 3:].eq(0).all(), "no gradient past the colour"


def test_gradcheck_float64():
    inputs = [x.requires_grad_(True) for x in _case(4, 3, 4, seed=2)]
    assert torch.autograd.gradcheck(composite, inputs)


def test_non_finite_values_are_data_and_threads_agree(monkeypatch, stability):
    front, transmittance, back = _case(64, 96, 4, dtype=torch.float32, seed=3)
    back[0, 0, 1] = float("nan")
    transmittance[1, 1] = float("inf")
    weights = torch.randn(64, 96, 3, generator=torch.Generator().manual_seed(4))
    runs = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        runs.append(_run(composite, (front, transmittance, back), weights))
    for run in runs[1:]:  # the same bits, NaNs included
        assert all(
            torch.equal(a.view(torch.int32), b.view(torch.int32))
            for a, b in zip(run, runs[0], strict=True)
        )
    out, _, v_t, _ = runs[0]
    assert out[0, 0, 1].isnan() and out[0, 0, [0, 2]].isfinite().all()
    assert v_t[0, 0].isnan() and out[1, 1].isinf().all()
    stability.checked(27, "composite: 1, 2, 3 threads, values and gradients", 4)


def test_bad_input_is_a_named_error(stability):
    front, transmittance, back = _case(dtype=torch.float32)
    bad = [
        (ShapeError, "front", (front[..., :2], transmittance, back)),
        (ShapeError, "front", (front, transmittance[:3], back)),
        (ShapeError, "front", (front, transmittance, back[:, :2])),
        (ShapeError, "transmittance", (front, transmittance[None], back)),
        (DTypeError, "transmittance", (front, transmittance.double(), back)),
        (DTypeError, "back", (front, transmittance, back.tolist())),
    ]
    for error, name, args in bad:
        with pytest.raises(error, match=name):
            composite(*args)
    with pytest.raises(Exception, match="back"):
        composite(front, transmittance, back[..., :2].contiguous())
    stability.checked(26, "composite: wrong shapes, dtypes and channel counts named", len(bad) + 1)


def test_avatar_render_is_the_gaussians_composited_over_the_mesh():
    """Avatar.render splats its Gaussians over the mesh in one pass: the same image, bit for
    bit, as splatting them over black and compositing that over the mesh, and the same
    gradients to the maps."""
    avatar = make_avatar(procedural_head(0), count=300)
    avatar.maps.requires_grad_(True)
    cam = camera(40)
    params = avatar.frame(3)

    def render(fused):
        avatar.maps.grad = None
        if fused:
            image = avatar.render(params, cam).image
        else:
            verts, rotations = avatar.skin(params)
            displaced, offsets = avatar.displace(verts, rotations)
            mesh = avatar.shade_mesh(displaced, offsets, rotations, cam, False)
            lift = avatar.lift_gaussians(verts, rotations, cam)
            alone = avatar.splat(lift, cam, mesh.depth)
            image = composite(alone.image, alone.transmittance, mesh.rgba)
        weights = torch.linspace(-1, 1, image.numel()).reshape(image.shape)
        (image * weights).sum().backward()
        return image.detach(), avatar.maps.grad.to_dense()

    (fused, fused_grad), (apart, apart_grad) = render(True), render(False)
    assert torch.equal(fused, apart)
    assert fused_grad.abs().max() > 0
    assert torch.allclose(fused_grad, apart_grad, rtol=1e-5, atol=1e-6 * fused_grad.abs().max())
