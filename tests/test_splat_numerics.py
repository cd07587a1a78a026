"""NUMERICS.md cases 9–21, 26 and 27 for rasterize_gaussians and normal_to_quat."""

import math

import numpy as np
import pytest
import torch

import urhead
from splat_scenes import camera, head_scene, requires_grad, weighted_loss
from urhead.errors import DTypeError, NonFiniteError, ShapeError, SizeLimitError
from urhead.ops import _reference as ref
from urhead.ops import normal_to_quat, rasterize_gaussians

CENTRE = 20.5  # principal point on a pixel centre: means on the optical axis hit σ = 0


def stacked(opacities, depths, dtype=torch.float64, scale=1e-4, size=64):
    """Gaussians on the optical axis (screen position = a pixel centre), one per depth."""
    n = len(opacities)
    means = torch.zeros(n, 3, dtype=dtype)
    means[:, 2] = torch.tensor(depths, dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype)
    scales = torch.full((n, 3), scale, dtype=dtype)
    opac = torch.tensor(opacities, dtype=dtype)
    return means, quats, scales, opac, camera(size, principal=(CENTRE, CENTRE))


def centre_loss(image, which=None):
    """A loss that reads only the centre pixel."""
    px = image[int(CENTRE), int(CENTRE)]
    return px.sum() if which is None else px[which]


def grads_finite(*tensors):
    return all(t is None or bool(torch.isfinite(t).all()) for t in tensors)


# 9 ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case09_means_at_extreme_depths(dtype, stability):
    near = float(np.float32(0.01))
    depths = [-1.0, 0.0, near - 1e-7, near + 1e-7, 1.0, 1e9]
    means, quats, scales, opac, cam = stacked([0.8] * 6, depths, dtype, scale=1e-3)
    means[:, 0] = torch.tensor([0, 0, 0, 0, 0.01, 0], dtype=dtype) * means[:, 2]
    m, s, o, c = requires_grad(means, scales, opac, torch.rand(6, 3, dtype=dtype))
    out = rasterize_gaussians(m, quats, s, o, c, cam)
    # Behind, at 0, just before near and beyond far: culled; just after near and at 1 m:
    # rendered.
    assert out.visible.tolist() == [False, False, False, True, True, False]
    stability.checked(9, "culled at z = −1, 0, near − 1e-7, 1e9; rendered at near + 1e-7, 1", 6)
    weighted_loss(out.image, out.transmittance).backward()
    assert grads_finite(out.image, m.grad, s.grad, o.grad, c.grad)
    culled_grad = max(m.grad[[0, 1, 2, 5]].abs().max(), c.grad[[0, 1, 2, 5]].abs().max())
    stability.record(9, "max |gradient| to culled means and colours", culled_grad, 0)
    assert (m.grad[[0, 1, 2, 5]] == 0).all() and (c.grad[[0, 1, 2, 5]] == 0).all()
    bad = means.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="means"):
        rasterize_gaussians(bad, quats, scales, opac, torch.rand(6, 3, dtype=dtype), cam)
    stability.checked(9, "NaN mean: NonFiniteError naming means")


# 10 --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("ratio", "clamped"), [((0.40, 0.0), True), ((0.20, -0.42), True), ((0.10, 0.05), False)]
)
def test_case10_offscreen_and_grazing_means_match_reference_and_fd(ratio, clamped, stability):
    cam = camera(64, principal=(20.0, 44.0))  # off-centre principal point
    fx = cam.fx
    lim_x = (64 - 20.0) / fx + 0.3 * 32 / fx
    lim_y = 44.0 / fx + 0.3 * 32 / fx
    assert (abs(ratio[0]) > lim_x or -ratio[1] > lim_y) == clamped
    z = 0.75
    means = torch.tensor([[ratio[0] * z, ratio[1] * z, z]], dtype=torch.float64)
    quats = torch.tensor([[0.9, 0.1, -0.3, 0.2]], dtype=torch.float64)
    scales = torch.tensor([[0.05, 0.02, 0.03]], dtype=torch.float64)
    opac = torch.tensor([0.9], dtype=torch.float64)
    colors = torch.tensor([[0.2, 0.7, 0.4]], dtype=torch.float64)

    def loss(fn, m, q, s):
        out = fn(m, q, s, opac, colors, cam)
        return weighted_loss(out[0], out[1])

    ours = requires_grad(means, quats, scales)
    loss(rasterize_gaussians, *ours).backward()
    theirs = requires_grad(means, quats, scales)
    loss(ref.rasterize_gaussians, *theirs).backward()
    branch = "clamped" if clamped else "unclamped"
    for a, b in zip(ours, theirs, strict=True):
        stability.close(
            10, f"{branch} branch: gradients vs float64 reference", a.grad, b.grad, 1e-9, 1e-12
        )
        assert torch.allclose(a.grad, b.grad, rtol=1e-9, atol=1e-12)
    assert ours[0].grad.abs().max() > 0
    g = torch.Generator().manual_seed(0)
    for k, x in enumerate((means, quats, scales)):
        d = torch.randn(x.shape, generator=g, dtype=torch.float64)
        args = [means, quats, scales]
        h = 1e-8
        args[k] = x + h * d
        up = loss(rasterize_gaussians, *args).item()
        args[k] = x - h * d
        down = loss(rasterize_gaussians, *args).item()
        fd = (up - down) / (2 * h)
        analytic = (ours[k].grad * d).sum().item()
        fd_err = abs(fd - analytic) / (1 + abs(fd))
        stability.record(
            10, f"{branch} branch: |gradient − central differences| / (1 + |FD|)", fd_err, 1e-6
        )
        assert abs(fd - analytic) <= 1e-6 * (1 + abs(fd)), (k, fd, analytic)


# 11 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case11_degenerate_scales_and_quaternions(dtype, stability):
    values = [0.0, 1e-30, math.exp(-100), 1e-3]
    n = len(values) + 1
    means, quats, _, opac, cam = stacked([0.7] * n, [0.5 + 0.1 * i for i in range(n)], dtype)
    scales = torch.tensor([[v, 1e-3, 1e-3] for v in values] + [[1e-3] * 3], dtype=dtype)
    quats[-1] = 0.0  # zero quaternion
    colors = torch.rand(n, 3, dtype=dtype)
    m, s, q = requires_grad(means, scales, quats)
    out = rasterize_gaussians(m, q, s, opac, colors, cam)
    weighted_loss(out.image, out.transmittance).backward()
    assert grads_finite(out.image, m.grad, s.grad, q.grad)
    tiny_is_normal = dtype == torch.float64 or torch.finfo(dtype).tiny <= 1e-30
    # Zero scale, subnormal scale (exp(−100) in float32) and zero quaternion: culled.
    # 1e-30 is a normal float in both dtypes: rendered as a dilated point.
    expect = [False, tiny_is_normal, dtype == torch.float64, True, False]
    assert out.visible.tolist() == expect
    stability.checked(
        11, "scales 0, 1e-30, exp(−100), zero quaternion: culled or a dilated point by rule", 5
    )
    culled_grad = max(q.grad[-1].abs().max(), s.grad[0].abs().max())
    stability.record(11, "max |gradient| to a zero quaternion / zero scale", culled_grad, 0)
    assert (q.grad[-1] == 0).all() and (s.grad[0] == 0).all()
    # exp(+100) overflows float32 (rejected); in float64 it is a huge, finite Gaussian.
    big = torch.tensor([[math.exp(100), 1e-3, 1e-3]], dtype=dtype)
    if dtype == torch.float32:
        with pytest.raises(NonFiniteError, match="scales"):
            rasterize_gaussians(means[:1], quats[:1], big, opac[:1], colors[:1], cam)
    else:
        out = rasterize_gaussians(means[:1], quats[:1], big, opac[:1], colors[:1], cam)
        assert torch.isfinite(out.image).all()
    stability.checked(11, "exp(100) scale: NonFiniteError (float32) or finite image (float64)")


@pytest.mark.parametrize("p", [0.3, 0.9, 0.995, 1.0])
def test_case11_alpha_never_exceeds_opacity(p, stability):
    means, quats, scales, opac, cam = stacked([p], [0.8], torch.float32, scale=2e-3)
    white = torch.ones(1, 3)
    out = rasterize_gaussians(means, quats, scales, opac, white, cam)
    alpha = 1 - out.transmittance
    stability.record(11, "max alpha − min(opacity, 0.99)", alpha.max() - min(p, 0.99), 1e-7)
    assert alpha.max() <= min(p, 0.99) + 1e-7
    assert alpha.max() >= min(p, 0.99) - 1e-6
    assert torch.allclose(out.image[..., 0], alpha, atol=1e-6)


# 12 --------------------------------------------------------------------------------------
def test_case12_huge_gaussians_bounded_or_error(stability):
    n = 2000
    means, quats, scales, opac, _ = stacked(
        [0.02] * n, [1.0 + 1e-3 * i for i in range(n)], torch.float32
    )
    cam = camera(512)
    scales[:] = 10.0  # metres: each covers the 512² image many times over
    out = rasterize_gaussians(means, quats, scales, opac, torch.rand(n, 3), cam)
    assert torch.isfinite(out.image).all() and out.visible.all()
    stability.checked(12, "2000 Gaussians of σ = 10 m on 512²: rendered, finite", 2000)
    # Enough of them to exceed the intersection limit: a size error, nothing allocated.
    n = 70_000
    many = torch.zeros(n, 3)
    many[:, 2] = 1.0
    with pytest.raises(SizeLimitError, match="intersections"):
        rasterize_gaussians(
            many,
            torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).contiguous(),
            torch.full((n, 3), 10.0),
            torch.full((n,), 0.5),
            torch.rand(n, 3),
            cam,
        )
    stability.checked(12, "70 000 of them: SizeLimitError naming intersections, before allocating")


# 13 --------------------------------------------------------------------------------------
def test_case13_ill_conditioned_covariance(stability):
    means, _, _, opac, cam = stacked([0.9, 0.8], [0.6, 0.7])
    # 45° about the view axis.
    quats = torch.tensor(
        [[math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)]] * 2, dtype=torch.float64
    )
    scales = torch.tensor([[1e-2, 1e-5, 1e-5], [1e-5, 1e-2, 1e-5]], dtype=torch.float64)
    colors = torch.tensor([[1.0, 0.2, 0.1], [0.1, 0.3, 1.0]], dtype=torch.float64)
    img, t, _ = ref.rasterize_gaussians(means, quats, scales, opac, colors, cam)
    for dtype in (torch.float32, torch.float64):
        args = [x.to(dtype) for x in (means, quats, scales, opac, colors)]
        out = rasterize_gaussians(*args, cam)
        tol = 2e-6 if dtype == torch.float32 else 1e-12
        err = max(
            (out.image.double() - img).abs().max(), (out.transmittance.double() - t).abs().max()
        )
        stability.record(
            13, f"max abs image/T error vs float64 reference ({str(dtype)[6:]})", err, tol
        )
        assert (out.image.double() - img).abs().max() < tol
        assert (out.transmittance.double() - t).abs().max() < tol
    assert (t < 0.9).sum() > 20, "the needles are rendered (dilated), not culled"


# 14 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case14_saturation_stops_after_three(dtype, stability):
    means, quats, scales, opac, cam = stacked([0.95] * 8, [1.0 + 0.1 * i for i in range(8)], dtype)
    colors = torch.eye(8, 3, dtype=dtype) + torch.arange(8, dtype=dtype)[:, None] / 10
    c = requires_grad(colors)[0]
    out = rasterize_gaussians(means, quats, scales, opac, c, cam)
    t_centre = out.transmittance[int(CENTRE), int(CENTRE)].item()
    t_err = abs(t_centre / 0.05**3 - 1)
    stability.record(14, f"relative error of the final T vs 0.05³ ({str(dtype)[6:]})", t_err, 1e-5)
    assert t_centre == pytest.approx(0.05**3, rel=1e-5)  # T = 1, 0.05, 2.5e-3, 1.25e-4, stop
    d = [x.double() for x in (means, quats, scales, opac)]
    m2d, conics, depths, radii, _ = ref.project_gaussians(*d, cam)
    _, _, all_t = ref.composite_gaussians(m2d, conics, colors.double(), d[3], depths, radii, 64, 64)
    ref_t = all_t[:, int(CENTRE), int(CENTRE)]
    expected_t = torch.tensor([0.05, 0.05**2] + [0.05**3] * 6, dtype=torch.float64)
    stability.close(14, "float64 reference T sequence vs 0.05^k", ref_t, expected_t, 1e-6, 1e-8)
    assert torch.allclose(ref_t, expected_t, rtol=1e-6)
    centre_loss(out.image).backward()
    g = c.grad.sum(-1)
    # The backward uses the same three samples: T_i·α_i for them, exactly 0 after.
    expected = torch.tensor([1.0, 0.05, 0.0025], dtype=torch.float64) * 0.95 * 3
    stability.close(
        14,
        f"colour gradient of the 3 samples = T_i·α_i ({str(dtype)[6:]})",
        g[:3],
        expected,
        1e-5,
        1e-8,
    )
    assert torch.allclose(g[:3].double(), expected, rtol=1e-5)
    stability.record(14, "max |colour gradient| after the stop", g[3:].abs().max(), 0)
    assert (g[3:] == 0).all()


# 15 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case15_sixteen_opaque_gaussians_clamped(dtype, stability):
    means, quats, scales, opac, cam = stacked(
        [1.0] * 16, [1.0 + 0.05 * i for i in range(16)], dtype, 1e-3
    )
    colors = torch.rand(16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    # Two samples at α = 0.99 leave T = 0.01² = T_stop exactly, so whether the third one
    # stops depends on rounding: the reference runs in the same dtype.
    d = [x.to(dtype) for x in (means, quats, scales, opac)]
    proj = ref.project_gaussians(*d, cam)
    img, t, all_t = ref.composite_gaussians(
        proj[0], proj[1], colors.to(dtype), d[3], proj[2], proj[3], 64, 64
    )
    assert all_t.shape[0] == 16
    o = requires_grad(opac)[0]
    out = rasterize_gaussians(means, quats, scales, o, colors.to(dtype), cam)
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    err = max((out.image - img).abs().max(), (out.transmittance - t).abs().max())
    stability.record(
        15, f"max abs image/T error vs reference storing every T_i ({str(dtype)[6:]})", err, tol
    )
    assert (out.image - img).abs().max() < tol
    assert (out.transmittance - t).abs().max() < tol
    d = [x.double() for x in d]
    assert torch.isfinite(out.image).all()
    # Convention: where min(0.99, o·g) clamps, α passes no gradient. At the centre pixel
    # every contributing sample is clamped, so a loss on that pixel gives o no gradient.
    centre_loss(out.image).backward()
    stability.record(15, "max |opacity gradient| through clamped alphas", o.grad.abs().max(), 0)
    assert (o.grad == 0).all()
    o_ref = requires_grad(d[3])[0]
    img2, _, _ = ref.rasterize_gaussians(d[0], d[1], d[2], o_ref, colors, cam)
    weighted_loss(img2, torch.zeros(64, 64, dtype=torch.float64)).backward()
    o2 = requires_grad(opac)[0]
    out = rasterize_gaussians(means, quats, scales, o2, colors.to(dtype), cam)
    weighted_loss(out.image, torch.zeros(64, 64, dtype=dtype)).backward()
    stability.close(
        15,
        f"opacity gradient vs float64 autograd ({str(dtype)[6:]})",
        o2.grad,
        o_ref.grad,
        1e-3,
        1e-5,
    )
    assert torch.allclose(o2.grad.double(), o_ref.grad, rtol=1e-3, atol=1e-5)


# 16 --------------------------------------------------------------------------------------
def test_case16_three_thousand_faint_gaussians(stability):
    n = 3000
    alpha = 1.02 / 255
    means, quats, scales, opac, cam = stacked(
        [alpha] * n, [0.5 + 1e-4 * i for i in range(n)], size=24
    )
    colors = torch.rand(n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    img, t, _ = ref.rasterize_gaussians(means, quats, scales, opac, colors, cam)
    out = rasterize_gaussians(*(x.float() for x in (means, quats, scales, opac, colors)), cam)
    t_err = (out.transmittance.double() - t).abs().max()
    stability.record(16, "float32 max abs T error vs float64 reference", t_err, 1e-5)
    assert (out.transmittance.double() - t).abs().max() < 1e-5
    img_err = (out.image.double() - img).abs().max()
    stability.record(16, "float32 max abs image error vs float64 reference", img_err, 1e-5)
    assert (out.image.double() - img).abs().max() < 1e-5
    k = int(math.log(1e-4) / math.log(1 - alpha))  # samples before the stop
    assert t[int(CENTRE), int(CENTRE)].item() == pytest.approx((1 - alpha) ** k, rel=1e-9)
    # Gradients through a tile list of thousands (the backward replays it in segments).
    grads = []
    for fn in (rasterize_gaussians, ref.rasterize_gaussians):
        o, c = requires_grad(opac, colors)
        out = fn(means, quats, scales, o, c, cam)
        weighted_loss(out[0], out[1]).backward()
        grads.append((o.grad, c.grad))
    for a, b in zip(*grads, strict=True):
        assert torch.isfinite(a).all()
        rel = (a - b).abs().max() / b.abs().max()
        stability.record(16, "float64 gradients vs autograd, max |a − b| / max |b|", rel, 1e-9)
        assert (a - b).abs().max() <= 1e-9 * b.abs().max()


# 17 --------------------------------------------------------------------------------------
def _stop_threshold_opacity():
    """The float32 o3 where T2·(1 − o3) crosses 1e-4 (T2 from o1 = 0.9, o2 = 0.95)."""
    f = np.float32
    t2 = f(f(1) * f(f(1) - f(0.9))) * f(f(1) - f(0.95))
    o3 = f(0.98)
    stop = f(1e-4)
    while f(t2 * f(f(1) - o3)) >= stop:
        o3 = np.nextafter(o3, f(1))
    while f(t2 * f(f(1) - o3)) < stop:
        o3 = np.nextafter(o3, f(0))
    return float(o3), float(np.nextafter(o3, f(1)))  # last contributing, first stopping


def test_case17_thresholds_at_one_ulp_decide_identically(stability):
    last_kept, first_stopped = _stop_threshold_opacity()
    thr = np.float32(1 / 255)
    cases = [
        # (opacities on the centre pixel, does the last one contribute?)
        ([float(np.nextafter(thr, np.float32(1)))], True),
        ([float(np.nextafter(thr, np.float32(0)))], False),
        ([0.9, 0.95, last_kept], True),
        ([0.9, 0.95, first_stopped], False),
    ]
    for opacities, contributes in cases:
        n = len(opacities)
        means, quats, scales, opac, cam = stacked(
            opacities, [0.5 + 0.1 * i for i in range(n)], torch.float32
        )
        colors = torch.zeros(n, 3)
        colors[-1, 0] = 1.0
        c = requires_grad(colors)[0]
        out = rasterize_gaussians(means, quats, scales, opac, c, cam)
        red = out.image[int(CENTRE), int(CENTRE), 0].item()
        centre_loss(out.image, 0).backward()
        wrong = int((red > 0) != contributes) + int((c.grad[-1, 0].item() != 0) != contributes)
        stability.record(17, "forward or backward deciding against the rule at ±1 ulp", wrong, 0)
        assert (red > 0) == contributes, opacities
        assert (c.grad[-1, 0].item() != 0) == contributes, opacities


# 18 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case18_tile_corner_sweep_has_no_seams(dtype, stability):
    cam = camera(64, principal=(32.0, 32.0))
    z = 0.8
    for k in range(-32, 33, 4):
        offset = 16 + k / 64  # pixel coordinate around the tile corner (16, 16)
        u = torch.tensor([offset, offset + 0.5 * k / 64], dtype=torch.float64)
        xy = (u - 32.0) * z / cam.fx
        means = torch.tensor([[xy[0], xy[1], z]], dtype=torch.float64)
        quats = torch.tensor([[0.9, 0.2, 0.1, -0.3]], dtype=torch.float64)
        scales = torch.tensor([[0.008, 0.004, 0.005]], dtype=torch.float64)
        opac = torch.tensor([0.9], dtype=torch.float64)
        colors = torch.tensor([[1.0, 0.5, 0.25]], dtype=torch.float64)
        img, t, _ = ref.rasterize_gaussians(means, quats, scales, opac, colors, cam)
        out = rasterize_gaussians(*(x.to(dtype) for x in (means, quats, scales, opac, colors)), cam)
        tol = 1e-6 if dtype == torch.float32 else 1e-12
        err = max(
            (out.image.double() - img).abs().max(), (out.transmittance.double() - t).abs().max()
        )
        stability.record(
            18, f"tiled vs untiled float64, max abs image/T error ({str(dtype)[6:]})", err, tol
        )
        assert (out.image.double() - img).abs().max() < tol, k
        assert (out.transmittance.double() - t).abs().max() < tol, k


# 19 --------------------------------------------------------------------------------------
def _z_axis(q):
    return ref.quat_to_rotmat(q)[..., :, 2]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case19_normal_to_quat_every_direction(dtype, stability):
    dirs = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    dirs += [[eps, 0, -1] for eps in (1.0, 1e-3, 1e-8, 1e-20, 1e-45, 0.0, -1e-20)]
    dirs += [[eps, 1e-3, 1] for eps in (1e-3, 0.0)]
    g = torch.Generator().manual_seed(0)
    rand = torch.randn(200, 3, generator=g, dtype=torch.float64)
    rand[::7, 2] = 0.0  # exactly in the n_z = 0 plane
    normals = torch.cat([torch.tensor(dirs, dtype=torch.float64), rand]).to(dtype)
    for magnitude in (1.0, 1e-30, 1e30):
        n = (normals * magnitude).requires_grad_(True)
        q = normal_to_quat(n)
        assert torch.isfinite(q).all()
        name = str(dtype)[6:]
        ones = torch.ones(len(q), dtype=dtype)
        stability.close(19, f"|q| = 1 ({name})", q.detach().norm(dim=-1), ones, 1e-5, 1e-6)
        assert torch.allclose(q.norm(dim=-1), torch.ones(len(q), dtype=dtype), atol=1e-6)
        unit = normals.double() / normals.double().norm(dim=-1, keepdim=True)
        z_axis = _z_axis(q.detach().double())
        stability.close(19, f"rotated z axis = unit normal ({name})", z_axis, unit, 1e-5, 1e-5)
        assert torch.allclose(_z_axis(q.double()), unit, atol=1e-5)
        (q * torch.randn(q.shape, generator=g, dtype=dtype)).sum().backward()
        assert torch.isfinite(n.grad).all()
    stability.checked(
        19, "finite quaternion and gradient, magnitudes 1, 1e-30, 1e30", 3 * len(normals)
    )


def test_case19_normal_to_quat_fallback_and_gradient(stability):
    bad = torch.tensor(
        [[0.0, 0, 0], [float("nan"), 0, 1], [float("inf"), 0, 0]], requires_grad=True
    )
    q = normal_to_quat(bad)
    assert torch.equal(q.detach(), torch.tensor([[1.0, 0, 0, 0]] * 3))
    q.sum().backward()
    assert (bad.grad == 0).all()
    stability.checked(19, "zero, NaN, inf normal: identity fallback, zero gradient", 3)
    n = torch.tensor([[0.3, -0.5, 0.8], [0.2, 0.4, -0.9]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(normal_to_quat, (n,))


# 20 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("distance", [0.5, 5.0])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case20_occlusion_against_mesh_depth(distance, dtype, stability):
    cam = camera(64, principal=(32.0, 32.0))
    depth = torch.full((64, 64), distance, dtype=dtype)
    eps = 5e-4  # half a millimetre: 1 mm behind is occluded, on the surface is not
    offsets = {"on": 0.0, "front": -1e-3, "behind": 1e-3}
    g = torch.Generator().manual_seed(2)
    for name, off in offsets.items():
        n = 10
        uv = torch.rand(n, 2, generator=g, dtype=torch.float64) * 40 + 12  # interior pixels
        z = torch.full((n,), distance + off, dtype=torch.float64)
        xy = (uv - 32.0) * z[:, None] / cam.fx
        means = torch.cat([xy, z[:, None]], -1).to(dtype)
        quats = torch.tensor([[1.0, 0, 0, 0]] * n, dtype=dtype)
        scales = torch.full((n, 3), 2e-3 * distance, dtype=dtype)
        opac = torch.full((n,), 0.8, dtype=dtype)
        colors = torch.ones(n, 3, dtype=dtype)
        out = rasterize_gaussians(
            means, quats, scales, opac, colors, cam, depth_map=depth, depth_eps=eps
        )
        free = rasterize_gaussians(means, quats, scales, opac, colors, cam)
        if name == "behind":
            leaked = ((out.image != 0).any(-1) | (out.transmittance != 1)).sum()
            stability.record(20, "1 mm behind: pixels a Gaussian still reaches", leaked, 0)
            assert (out.image == 0).all() and (out.transmittance == 1).all()
        else:
            changed = (out.image != free.image).any(-1).sum()
            stability.record(
                20, "on the surface / 1 mm in front: pixels changed by occlusion", changed, 0
            )
            assert torch.equal(out.image, free.image), name
        assert free.image.amax() > 0.5


# 21 --------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case21_empty_culled_and_single_pixel(dtype, stability):
    cam = camera(64)
    bg = torch.tensor([0.25, 0.5, 0.75], dtype=dtype, requires_grad=True)
    empty = [torch.zeros(0, k, dtype=dtype, requires_grad=True) for k in (3, 4, 3)]
    o = torch.zeros(0, dtype=dtype, requires_grad=True)
    c = torch.zeros(0, 3, dtype=dtype, requires_grad=True)
    out = rasterize_gaussians(*empty, o, c, cam, bg)
    assert torch.equal(out.image, bg.detach().expand(64, 64, 3))
    assert (out.transmittance == 1).all()
    out.image.sum().backward()
    assert all(t.grad is not None and t.grad.shape == t.shape for t in (*empty, o, c))
    assert torch.allclose(bg.grad, torch.full((3,), 64.0 * 64, dtype=dtype))
    stability.checked(21, "zero Gaussians: background image, empty gradients, background gradient")
    # All culled (behind the camera).
    means, quats, scales, opac, _ = stacked([0.5] * 3, [-1.0, -2.0, -3.0], dtype)
    m, cc = requires_grad(means, torch.rand(3, 3, dtype=dtype))
    out = rasterize_gaussians(m, quats, scales, opac, cc, cam, bg.detach())
    assert torch.equal(out.image, bg.detach().expand(64, 64, 3))
    out.image.sum().backward()
    assert (m.grad == 0).all() and (cc.grad == 0).all()
    stability.checked(21, "all culled: background image, zero gradients", 3)
    # A 1×1 image.
    one = camera(1, principal=(0.5, 0.5))
    means, quats, scales, opac, _ = stacked([0.6, 0.7], [0.5, 0.6], dtype, scale=2e-3)
    colors = torch.rand(2, 3, dtype=dtype)
    out = rasterize_gaussians(means, quats, scales, opac, colors, one)
    img, _, _ = ref.rasterize_gaussians(
        *(x.double() for x in (means, quats, scales, opac, colors)), one
    )
    err = (out.image.double() - img).abs().max()
    stability.record(
        21, f"1×1 image, max abs error vs float64 reference ({str(dtype)[6:]})", err, 1e-6
    )
    assert out.image.shape == (1, 1, 3) and (out.image.double() - img).abs().max() < 1e-6


# 26 --------------------------------------------------------------------------------------
def test_case26_bad_inputs_raise_named_errors(stability):
    means, quats, scales, opac, sh, cam = head_scene(10, torch.float32)
    ok = dict(means=means, quats=quats, scales=scales, opacities=opac, colors=sh, camera=cam)

    def call(**kw):
        return rasterize_gaussians(**{**ok, **kw})

    for name in ("means", "quats", "scales", "opacities", "colors"):
        for bad_value in (float("nan"), float("inf")):
            t = ok[name].clone()
            t.view(-1)[3] = bad_value
            with pytest.raises(NonFiniteError, match="sh" if name == "colors" else name):
                call(**{name: t})
    with pytest.raises(ShapeError, match="quats"):
        call(quats=quats[:, :3].contiguous())
    with pytest.raises(DTypeError, match="scales"):
        call(scales=scales.double())
    with pytest.raises(DTypeError, match="means"):
        call(means=means.half())
    with pytest.raises(ValueError, match="contiguous"):
        call(means=torch.zeros(3, 10).T)
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize_gaussians(means, quats, scales, opac, sh[:, :4].contiguous(), cam, sh_degree=2)
    depth = torch.full((64, 64), 1.0)
    depth[5, 5] = float("nan")
    with pytest.raises(NonFiniteError, match="depth_map"):
        call(depth_map=depth)
    with pytest.raises(ShapeError, match="depth_map"):
        call(depth_map=torch.ones(32, 64))
    with pytest.raises(ShapeError, match="background"):
        call(background=torch.ones(4))
    for k in ([[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]], [[0.0, 0, 1], [0, 1, 1], [0, 0, 1]]):
        with pytest.raises(ValueError, match="K"):
            urhead.Camera(torch.tensor(k), torch.eye(4), 64, 64)
    view = torch.eye(4)
    view[0, 3] = float("inf")
    with pytest.raises(ValueError, match="viewmat"):
        urhead.Camera(cam.K, view, 64, 64)
    with pytest.raises(ValueError, match="width"):
        urhead.Camera(cam.K, torch.eye(4), 0, 64)
    stability.checked(
        26,
        "splatting: NaN/inf in 5 inputs; bad shape, dtype, layout, sh_degree, depth map, "
        "background, K, viewmat, width → named error",
        22,
    )


# 27 --------------------------------------------------------------------------------------
def test_case27_bitwise_identical_for_any_thread_count(monkeypatch, stability):
    means, quats, scales, opac, sh, cam = head_scene(2000, torch.float32, seed=11, size=96)
    depth = torch.full((96, 96), 0.76)

    def run():
        ins = requires_grad(means, quats, scales, opac, sh)
        out = rasterize_gaussians(*ins, cam, depth_map=depth)
        out.means2d.retain_grad()
        weighted_loss(out.image, out.transmittance).backward()
        return [out.image, out.transmittance, out.means2d.grad] + [t.grad for t in ins]

    monkeypatch.setenv("URHEAD_NUM_THREADS", "1")
    reference = run()
    for threads in ("1", "2", "4", "2", "1", "4", "3", "2", "4", "1"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        for a, b in zip(run(), reference, strict=True):
            stability.record(
                27, "splatting: elements differing from the 1-thread run", (a != b).sum(), 0
            )
            assert torch.equal(a, b)
