"""Losses and metrics against direct references and known values."""

import math

import pytest
import torch
import torch.nn.functional as F

from urhead.head.mesh import uniform_laplacian
from urhead.losses import l1, psnr, ssim
from urhead.ops._reference import ssim_map
from urhead.train.objective import laplacian_loss


def reference_ssim_map(x, y):
    """Non-separable 2-D window, per channel, written out from the SSIM definition."""
    t = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(t**2) / (2 * 1.5**2))
    window = torch.outer(g, g)
    window = (window / window.sum())[None, None]
    maps = []
    for c in range(x.shape[2]):
        a = x[..., c].double()[None, None]
        b = y[..., c].double()[None, None]

        def blur(z):
            return F.conv2d(z, window, padding=5)[0, 0]

        mu_a, mu_b = blur(a), blur(b)
        var_a = blur(a * a) - mu_a**2
        var_b = blur(b * b) - mu_b**2
        cov = blur(a * b) - mu_a * mu_b
        maps.append(
            ((2 * mu_a * mu_b + 1e-4) * (2 * cov + 9e-4))
            / ((mu_a**2 + mu_b**2 + 1e-4) * (var_a + var_b + 9e-4))
        )
    return torch.stack(maps).mean(0)


def test_ssim_matches_direct_definition():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(40, 33, 3, generator=g)
    noise = torch.randn(40, 33, 3, generator=g)
    y = (x + 0.1 * noise).clamp(0, 1)
    assert (ssim_map(x, y).double() - reference_ssim_map(x, y)).abs().max() < 1e-5
    assert abs(ssim(x, x).item() - 1) < 1e-6
    noisier = (x + 0.3 * noise).clamp(0, 1)
    assert ssim(x, noisier).item() < ssim(x, y).item() < 1 - 1e-3


def test_masked_metrics_ignore_outside_pixels():
    x = torch.zeros(8, 8, 3)
    y = torch.zeros(8, 8, 3)
    y[:, 4:] = 1.0  # differs only outside the mask
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[:, :4] = True
    assert l1(x, y, mask).item() == 0
    y[0, 0] = 0.1
    expected_mse = 3 * 0.01 / (32 * 3)
    assert math.isclose(psnr(x, y, mask).item(), -10 * math.log10(expected_mse), rel_tol=1e-5)


def test_laplacian_of_a_flat_regular_grid_is_zero_inside():
    n = 6
    ys, xs = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    verts = torch.stack([xs, ys, torch.zeros_like(xs)], -1).reshape(-1, 3).float()
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            i = r * n + c
            faces += [[i, i + 1, i + n + 1], [i, i + n + 1, i + n]]
    lap = uniform_laplacian(torch.tensor(faces), n * n)
    deltas = torch.from_numpy(lap @ verts.numpy()).reshape(n, n, 3)
    # the two-diagonal-free interior vertex has 6 symmetric neighbours: δ = 0
    assert deltas[1:-1, 1:-1].abs().max() < 1e-6
    bumped = verts.clone()
    bumped[2 * n + 2, 2] = 1.0
    assert laplacian_loss(bumped, lap) > laplacian_loss(verts, lap) + 1e-3


def test_laplacian_loss_matches_the_dense_torch_expression_and_its_gradient():
    """Value and gradient against (1/V)·Σ‖L·v‖² with L dense in float64, for one mesh and
    a batch of two."""
    from urhead.head import procedural_head

    head = procedural_head(0)
    lap = uniform_laplacian(torch.tensor(head.faces), head.num_vertices)
    dense = torch.from_numpy(lap.toarray()).double()
    g = torch.Generator().manual_seed(0)
    for shape in ((head.num_vertices, 3), (2, head.num_vertices, 3)):
        verts = torch.randn(shape, generator=g)
        ours_v = verts.clone().requires_grad_(True)
        ours = laplacian_loss(ours_v, lap)
        ours.backward()
        ref_v = verts.double().requires_grad_(True)
        ref = ((dense @ ref_v) ** 2).sum(-1).mean()
        ref.backward()
        assert ours.dtype == torch.float32 and ours_v.grad.shape == shape
        assert abs(ours.item() - ref.item()) <= 1e-6 * ref.item()
        assert torch.allclose(ours_v.grad.double(), ref_v.grad, rtol=1e-5, atol=1e-9)


def test_the_objective_is_the_papers_photometric_loss_with_its_terms_weighted_in_kernel():
    """(1 − λ)·((1 − m)·L1(I) + m·L1(I_mesh)) + λ·(1 − SSIM(I)), as the paper writes it, with
    the weights folded into the kernels: the same value and gradients (to rounding) as the
    composition of unweighted terms, for the image and the mesh's RGBA, with and without
    the Gaussian branch."""
    from types import SimpleNamespace

    from urhead.train.objective import Objective

    g = torch.Generator().manual_seed(5)
    target = torch.rand(40, 36, 3, generator=g)
    image0 = (target + 0.2 * torch.randn(40, 36, 3, generator=g)).clamp(0, 1)
    rgba0 = torch.rand(40, 36, 4, generator=g)
    objective = Objective(
        lambda_ssim=0.2,
        mesh_term=0.2,
        lambda_normal=0.0,
        lambda_laplacian=0.0,
        laplacian=None,
        use_normals=False,
    )
    for gaussians in (SimpleNamespace(lift=SimpleNamespace(offset=None)), None):
        image, rgba = image0.clone().requires_grad_(True), rgba0.clone().requires_grad_(True)
        render = SimpleNamespace(image=image, mesh=SimpleNamespace(rgba=rgba), gaussians=gaussians)
        loss = objective(render, SimpleNamespace(image=target))
        loss.backward()
        image_ref = image0.double().requires_grad_(True)
        rgba_ref = rgba0.double().requires_grad_(True)
        t = target.double()
        photo = l1(image_ref, t)
        if gaussians is not None:
            photo = 0.8 * photo + 0.2 * l1(rgba_ref, t)
        expected = 0.8 * photo + 0.2 * (1 - ssim(image_ref, t))
        expected.backward()
        assert loss.item() == pytest.approx(expected.item(), rel=1e-6)
        assert (image.grad.double() - image_ref.grad).abs().max() < 1e-9
        if gaussians is not None:
            assert (rgba.grad.double() - rgba_ref.grad).abs().max() < 1e-9
            assert rgba.grad[..., 3].abs().max() == 0  # alpha is not compared
        else:
            assert rgba.grad is None
