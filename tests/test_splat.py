"""rasterize_gaussians against the plain-torch float64 references (forward and gradients)
and float64 finite differences."""

import pytest
import torch

from splat_scenes import camera, head_scene, requires_grad, weighted_loss
from urhead.errors import ShapeError
from urhead.ops import _reference as ref
from urhead.ops import rasterize_gaussians


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("with_depth", [False, True])
def test_image_matches_untiled_reference(dtype, with_depth):
    means, quats, scales, opac, sh, cam = head_scene(300, dtype)
    bg = torch.tensor([0.1, 0.5, 0.9], dtype=dtype)
    depth = None
    if with_depth:
        # A tilted plane through the head: about half of the samples are occluded.
        depth = (0.73 + 0.001 * torch.arange(64, dtype=dtype))[None, :].expand(64, 64).contiguous()
    out = rasterize_gaussians(means, quats, scales, opac, sh, cam, bg, depth)
    d = [t.double() for t in (means, quats, scales, opac, sh, bg)]
    img, t, means2d = ref.rasterize_gaussians(
        *d[:5], cam, d[5], None if depth is None else depth.double()
    )
    # Worst observed: 8e-7 (float32), 2e-15 (float64).
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    assert (out.image.double() - img).abs().max() < tol
    assert (out.transmittance.double() - t).abs().max() < tol
    assert (out.means2d.double() - means2d).abs().max() < 1e-3 * (
        1 if dtype == torch.float32 else 1e-9
    )
    assert img.std() > 0.05 and (t < 0.5).any(), "scene is not trivial"
    if with_depth:
        full = ref.rasterize_gaussians(*d[:5], cam, d[5])[0]
        assert (full - img).abs().max() > 0.1, "the depth map occludes something"


@pytest.mark.parametrize("with_depth", [False, True])
def test_gradients_match_reference_autograd(with_depth):
    means, quats, scales, opac, sh, cam = head_scene(150, torch.float64, seed=3)
    bg = torch.tensor([0.3, 0.2, 0.7], dtype=torch.float64)
    depth = torch.full((64, 64), 0.75, dtype=torch.float64) if with_depth else None

    def run(fn):
        m, q, s, o, c, b = requires_grad(means, quats, scales, opac, sh, bg)
        out = fn(m, q, s, o, c, cam, b, depth)
        means2d = out[2]
        means2d.retain_grad()
        weighted_loss(out[0], out[1]).backward()
        return [m.grad, q.grad, s.grad, o.grad, c.grad, b.grad, means2d.grad]

    ours = run(rasterize_gaussians)
    theirs = run(ref.rasterize_gaussians)
    names = ["means", "quats", "scales", "opacities", "sh", "background", "means2d"]
    for name, a, b in zip(names, ours, theirs, strict=True):
        err = (a - b).abs().max() / b.abs().max()
        # Worst observed relative error 5e-15.
        assert err < 1e-12, f"{name}: relative error {err}"
        assert b.abs().max() > 0


def test_float32_gradients_close_to_float64_reference():
    means, quats, scales, opac, sh, cam = head_scene(150, torch.float64, seed=4)

    def run(fn, dtype):
        m, q, s, o, c = requires_grad(*(t.to(dtype) for t in (means, quats, scales, opac, sh)))
        out = fn(m, q, s, o, c, cam)
        weighted_loss(out[0], out[1]).backward()
        return [m.grad, q.grad, s.grad, o.grad, c.grad]

    ours = run(rasterize_gaussians, torch.float32)
    theirs = run(ref.rasterize_gaussians, torch.float64)
    for a, b in zip(ours, theirs, strict=True):
        a = a.double()
        cos = (a * b).sum() / (a.norm() * b.norm())
        rel = (a - b).norm() / b.norm()
        # Worst observed: relative L2 1e-6, cosine 1 − 1e-12.
        assert rel < 1e-5 and cos > 1 - 1e-9, (rel, cos)


def test_direct_colors_any_channel_count():
    means, quats, scales, opac, _, cam = head_scene(100, torch.float64, seed=5)
    colors = torch.rand(100, 5, dtype=torch.float64)
    bg = torch.rand(5, dtype=torch.float64)

    def run(fn):
        m, c, b = requires_grad(means, colors, bg)
        out = fn(m, quats, scales, opac, c, cam, b)
        weighted_loss(out[0], out[1]).backward()
        return out[0].detach(), m.grad, c.grad, b.grad

    ours, theirs = run(rasterize_gaussians), run(ref.rasterize_gaussians)
    assert ours[0].shape == (64, 64, 5)
    for a, b in zip(ours, theirs, strict=True):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_degrees(degree):
    means, quats, scales, opac, sh, cam = head_scene(80, torch.float64, seed=6)

    def run(fn):
        m, c = requires_grad(means, sh)
        out = fn(m, quats, scales, opac, c, cam, sh_degree=degree)
        weighted_loss(out[0], out[1]).backward()
        return out[0].detach(), m.grad, c.grad

    ours, theirs = run(rasterize_gaussians), run(ref.rasterize_gaussians)
    for a, b in zip(ours, theirs, strict=True):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)
    # Coefficients beyond the degree get exactly zero gradient.
    assert (ours[2][:, (degree + 1) ** 2 :] == 0).all()


def _directional_fd(make_loss, x, h=1e-8, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(x.shape, generator=g, dtype=x.dtype)
    xg = x.clone().requires_grad_(True)
    make_loss(xg).backward()
    analytic = (xg.grad * d).sum().item()
    with torch.no_grad():
        fd = (make_loss(x + h * d) - make_loss(x - h * d)).item() / (2 * h)
    return analytic, fd


@pytest.mark.parametrize("which", ["means", "quats", "scales", "opacities", "sh"])
def test_gradients_match_finite_differences(which):
    inputs = list(head_scene(60, torch.float64, seed=7, scale=(-4.5, -3.0)))
    cam = inputs.pop()
    index = ["means", "quats", "scales", "opacities", "sh"].index(which)
    depth = torch.full((64, 64), 0.76, dtype=torch.float64)

    def loss(x):
        args = list(inputs)
        args[index] = x
        out = rasterize_gaussians(*args, cam, depth_map=depth)
        return weighted_loss(out.image, out.transmittance)

    # h is small enough that no pixel crosses the 1/255 cut-off (a discontinuity).
    analytic, fd = _directional_fd(loss, inputs[index])
    assert abs(analytic - fd) <= 1e-6 * (1 + abs(fd)), (analytic, fd)
    assert abs(fd) > 1e-3


def test_transmittance_is_differentiable_and_compositing_uses_it():
    means, quats, scales, opac, sh, cam = head_scene(100, torch.float64, seed=8)
    behind = torch.rand(64, 64, 3, dtype=torch.float64)

    def run(fn):
        o = requires_grad(opac)[0]
        out = fn(means, quats, scales, o, sh, cam)
        composite = out[0] + out[1][..., None] * behind
        composite.square().sum().backward()
        return o.grad

    assert torch.allclose(run(rasterize_gaussians), run(ref.rasterize_gaussians), rtol=1e-10)


@pytest.mark.parametrize(("with_depth", "size"), [(False, 64), (True, 64), (False, 45)])
def test_an_image_background_is_the_composite_over_it(with_depth, size):
    """An (H, W, S) background (here RGBA-like, S = 4 > C = 3) is the Gaussians over black
    composited over its colour, forward and backward (float64 reference autograd), its own
    gradient T·v_image and zero past the colour; 45² ends in partial tiles and chunks."""
    means, quats, scales, opac, sh, cam = head_scene(150, torch.float64, seed=11, size=size)
    g = torch.Generator().manual_seed(5)
    behind = torch.rand(size, size, 4, generator=g, dtype=torch.float64)
    depth = torch.full((size, size), 0.75, dtype=torch.float64) if with_depth else None

    def run(fused):
        m, q, s, o, c, b = requires_grad(means, quats, scales, opac, sh, behind)
        if fused:
            out = rasterize_gaussians(m, q, s, o, c, cam, b, depth)
            image, t = out.image, out.transmittance
        else:
            image, t, _ = ref.rasterize_gaussians(m, q, s, o, c, cam, None, depth)
            image = image + t[..., None] * b[..., :3]
        weighted_loss(image, t).backward()
        return image.detach(), [m.grad, q.grad, s.grad, o.grad, c.grad, b.grad]

    (ours, ours_grads), (theirs, their_grads) = run(True), run(False)
    assert (ours - theirs).abs().max() < 1e-12
    names = ["means", "quats", "scales", "opacities", "sh", "background"]
    for name, a, b in zip(names, ours_grads, their_grads, strict=True):
        err = (a - b).abs().max() / b.abs().max()
        assert err < 1e-12, f"{name}: relative error {err}"
    assert torch.equal(ours_grads[5][..., 3], torch.zeros(size, size, dtype=torch.float64))
    assert (ours - behind[..., :3]).abs().max() > 0.1, "the Gaussians cover something"


def test_an_image_background_in_float32_is_the_float32_composite_bit_for_bit():
    """Over black and then composited (as `composite` does) or composited in the same
    pass: acc + T·behind either way, the same float32 operations."""
    from urhead.ops import composite

    means, quats, scales, opac, sh, cam = head_scene(300, torch.float32, seed=12)
    behind = torch.rand(64, 64, 4, generator=torch.Generator().manual_seed(6))
    behind[3, 5, 0] = float("nan")  # data, not an error: it shows where T > 0
    fused = rasterize_gaussians(means, quats, scales, opac, sh, cam, behind)
    alone = rasterize_gaussians(means, quats, scales, opac, sh, cam)
    expected = composite(alone.image, alone.transmittance, behind)
    assert torch.equal(fused.image.nan_to_num(7.0), expected.nan_to_num(7.0))
    assert torch.isnan(fused.image[3, 5, 0]) and torch.isnan(expected[3, 5, 0])
    assert torch.equal(fused.transmittance, alone.transmittance)


def test_a_background_of_the_wrong_shape_is_named():
    means, quats, scales, opac, sh, cam = head_scene(20, torch.float32)
    for bad in (
        torch.zeros(64, 64, 2),
        torch.zeros(32, 64, 4),
        torch.zeros(4),
        torch.zeros(64, 64),
    ):
        with pytest.raises(ShapeError, match="background"):
            rasterize_gaussians(means, quats, scales, opac, sh, cam, bad)


def test_densification_outputs():
    means, quats, scales, opac, sh, cam = head_scene(200, torch.float64, seed=9)
    means[0, 2] = -1.0  # behind the camera
    out = rasterize_gaussians(means, quats, scales, opac, sh, cam)
    _, _, _, radii, _ = ref.project_gaussians(means, quats, scales, opac, cam)
    assert out.radii.dtype == torch.int32 and out.radii.shape == (200, 2)
    assert torch.equal(out.radii, radii)
    assert not out.visible[0] and out.visible[1:].sum() > 150
    assert torch.equal(out.visible, (radii > 0).all(-1))


def test_camera_with_offcentre_principal_point_and_partial_tiles():
    means, quats, scales, opac, sh, _ = head_scene(150, torch.float64, seed=10)
    cam = camera(45, width=83, principal=(30.0, 20.0))  # neither side a multiple of 16
    depth = torch.full((45, 83), 0.76, dtype=torch.float64)

    def run(fn):
        m, c = requires_grad(means, sh)
        out = fn(m, quats, scales, opac, c, cam, None, depth)
        weighted_loss(out[0], out[1]).backward()
        return out[0].detach(), out[1].detach(), m.grad, c.grad

    ours, theirs = run(rasterize_gaussians), run(ref.rasterize_gaussians)
    assert ours[0].shape == (45, 83, 3)
    for a, b in zip(ours, theirs, strict=True):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_row_and_chunk_skipping_is_conservative(dtype):
    # Needles and discs from sub-pixel to wider than the image, at every angle: the tile
    # loop visits only rows/chunks its analytic extent admits, and must not miss a pixel
    # whose alpha passes 1/255 (a miss would differ from the untiled reference by ≥ 1/255).
    g = torch.Generator().manual_seed(12)
    n = 40
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.03
    means[:, 2] = 0.5 + torch.rand(n, generator=g, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(-9, -1, generator=g))
    opac = torch.empty(n, dtype=torch.float64).uniform_(0.01, 1.0, generator=g)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    cam = camera(96, width=80, principal=(37.3, 51.7))
    img, t, _ = ref.rasterize_gaussians(means, quats, scales, opac, colors, cam)
    out = rasterize_gaussians(*(x.to(dtype) for x in (means, quats, scales, opac, colors)), cam)
    if dtype == torch.float64:
        assert (out.image - img).abs().max() < 1e-12
        assert (out.transmittance - t).abs().max() < 1e-12
    else:
        # Gaussians larger than the image lose float32 precision in the EWA chain (worst
        # observed: image 2.2e-5, T relative 1.1e-4 — the float32 reference itself differs
        # from float64 by as much); a skipped sample would change T by ≥ 1/255 relative.
        assert (out.image.double() - img).abs().max() < 1e-4
        assert ((out.transmittance.double() - t).abs() <= 3e-4 * t + 1e-7).all()
