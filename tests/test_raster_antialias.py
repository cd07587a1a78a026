"""urhead.ops.antialias against the reference, finite differences (NUMERICS.md case 6),
silhouette rules and topology."""

import math

import pytest
import torch

from raster_meshes import camera, identity_camera, uv_sphere
from urhead import ops
from urhead.ops import _reference as ref


def rel_err(a, b):
    return float((a - b).norm() / b.norm())


def two_spheres():
    """A sphere partly in front of a larger one: silhouettes against the background and
    against other geometry."""
    v1, f1, _, _ = uv_sphere(10, 14, radius=1.0, jitter=0.03, seed=11)
    v2, f2, _, _ = uv_sphere(8, 12, radius=0.5, jitter=0.02, seed=12)
    v2 = v2 + torch.tensor([0.55, -0.3, -1.2], dtype=torch.float64)
    return torch.cat([v1, v2]), torch.cat([f1, f2 + v1.shape[0]])


SCENES = [
    dict(eye=(0.3, 0.2, -3.0)),
    dict(eye=(2.0, -1.2, -2.0), fov=35.0),
    dict(eye=(-0.5, 0.8, -2.4), fov=50.0),
]


@pytest.mark.parametrize("cam_args", SCENES)
def test_forward_and_gradients_match_reference(cam_args):
    verts, faces = two_spheres()
    cam = camera(width=40, height=36, **cam_args)
    raster = ops.rasterize(verts, faces, cam)
    g = torch.Generator().manual_seed(1)
    color = torch.rand(cam.height, cam.width, 3, dtype=torch.float64, generator=g)
    color.requires_grad_(True)
    v = verts.clone().requires_grad_(True)
    out = ops.antialias(color, raster, v, faces, cam)
    expected = ref.antialias(color, raster, v, faces, cam)
    changed = (out != color).any(-1)
    assert changed.sum() > 40
    # A few ulps of float64: the worst seen is 3.3e-15 with torch 2.15's reference ops
    # (≤ 1e-15 with earlier torch, whose elementwise kernels rounded in another order).
    assert (out - expected).abs().max() < 8e-15
    weights = torch.randn(out.shape, dtype=torch.float64, generator=g)
    grads = torch.autograd.grad((out * weights).sum(), (color, v))
    e_grads = torch.autograd.grad((expected * weights).sum(), (color, v))
    assert rel_err(grads[0], e_grads[0]) < 1e-14
    assert rel_err(grads[1], e_grads[1]) < 1e-13
    assert grads[1].abs().sum() > 0


def test_float32_agrees_with_float64():
    verts, faces = two_spheres()
    cam = camera(width=40, height=36)
    color = torch.rand(
        cam.height, cam.width, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)
    )
    weights = torch.randn(
        color.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3)
    )

    def run(dtype):
        c = color.to(dtype).requires_grad_(True)
        v = verts.to(dtype).requires_grad_(True)
        r = ops.rasterize(v.detach(), faces, cam)
        out = ops.antialias(c, r, v, faces, cam)
        return (out, *torch.autograd.grad((out * weights.to(dtype)).sum(), (c, v)))

    out32, c32, v32 = run(torch.float32)
    out64, c64, v64 = run(torch.float64)
    assert (out32.double() - out64).abs().max() < 2e-6
    assert rel_err(c32.double(), c64) < 5e-7
    assert rel_err(v32.double(), v64) < 2e-6


def test_topology_matches_reference():
    verts, faces = two_spheres()
    faces = torch.cat([faces, torch.tensor([[0, 0, 1], [0, 1, 2]], dtype=torch.int32)])
    topo = ops.antialias_topology(faces, verts.shape[0])
    assert topo.dtype == torch.int32 and topo.shape == faces.shape
    assert topo.tolist() == ref.edge_topology(faces)


# --- NUMERICS.md case 6 -------------------------------------------------------------------


def square_scene(offset, welded=True, angle=0.13):
    """A 2-triangle square (about 18 px) facing the camera, rotated in-plane, translated by
    ``offset`` (3,); coloured flat against a background."""
    cam = identity_camera(32, 32, focal=40.0)
    c, s = math.cos(angle), math.sin(angle)
    corners = torch.tensor(
        [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]], dtype=torch.float64
    )
    corners = corners @ torch.tensor([[c, s], [-s, c]], dtype=torch.float64) * 0.45
    verts = torch.cat([corners, torch.full((4, 1), 2.0, dtype=torch.float64)], 1) + offset
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]], dtype=torch.int32)
    if not welded:  # the second triangle gets its own copies of the diagonal's vertices
        verts = torch.cat([verts, verts[[0, 2]]])
        faces = torch.tensor([[0, 1, 2], [4, 5, 3]], dtype=torch.int32)
    return cam, verts, faces


def shaded(verts, faces, cam):
    raster = ops.rasterize(verts.detach(), faces, cam)
    fg = torch.tensor([0.9, 0.3, 0.1], dtype=torch.float64)
    bg = torch.tensor([0.1, 0.2, 0.7], dtype=torch.float64)
    color = torch.where((raster.tri_id >= 0)[..., None], fg, bg)
    return ops.antialias(color, raster, verts, faces, cam), raster


@pytest.mark.parametrize("offset", [(0.013, -0.021, 0.0), (0.031, 0.007, 0.0), (-0.02, 0.04, 0.1)])
def test_case6_translation_gradient_matches_finite_differences(offset, stability):
    # The loss weighs the red channel by a ramp in x and y (the image's first moment), so
    # its derivative under translation is well-conditioned: random-sign weights would
    # cancel out along the edges.
    ys, xs = torch.meshgrid(
        torch.arange(32, dtype=torch.float64) + 0.5,
        torch.arange(32, dtype=torch.float64) + 0.5,
        indexing="ij",
    )
    weights = torch.zeros(32, 32, 3, dtype=torch.float64)
    weights[..., 0] = (xs - 16) / 16 + 0.5 * (ys - 16) / 16
    base = torch.tensor(offset, dtype=torch.float64)

    def loss(t):
        cam, verts, faces = square_scene(t)
        return float((shaded(verts, faces, cam)[0] * weights).sum())

    cam, verts, faces = square_scene(base)
    v = verts.clone().requires_grad_(True)
    out, _ = shaded(v, faces, cam)
    (g,) = torch.autograd.grad((out * weights).sum(), v)
    analytic = g.sum(0)[:2]  # translation in x and y
    # Central differences over ±0.25 px: the antialiased image is continuous along the
    # edges (the blend follows the crossing point) and jumps only at a few corner pixels.
    h = 0.25 * 2.0 / 40.0
    steps = torch.eye(3, dtype=torch.float64)[:2] * h
    fd = torch.tensor(
        [(loss(base + d) - loss(base - d)) / (2 * h) for d in steps], dtype=torch.float64
    )
    cosine = float(analytic @ fd / (analytic.norm() * fd.norm()))
    stability.record(6, "1 − cosine(translation gradient, central differences)", 1 - cosine, 0.05)
    assert cosine >= 0.95, (analytic, fd)
    magnitude_err = abs(float(analytic.norm() / fd.norm()) - 1)
    stability.record(6, "|‖gradient‖ / ‖central differences‖ − 1|", magnitude_err, 0.10)
    assert abs(float(analytic.norm() / fd.norm()) - 1) <= 0.10, (analytic, fd)


def touches_background(tri_id):
    bg = tri_id < 0
    near = bg.clone()
    near[1:] |= bg[:-1]
    near[:-1] |= bg[1:]
    near[:, 1:] |= bg[:, :-1]
    near[:, :-1] |= bg[:, 1:]
    return near


def test_case6_shared_interior_edges_of_a_welded_mesh_produce_no_writes(stability):
    offset = torch.tensor([0.013, -0.021, 0.0], dtype=torch.float64)
    cam, verts, faces = square_scene(offset)
    out, raster = shaded(verts, faces, cam)
    plain = torch.where(
        (raster.tri_id >= 0)[..., None],
        torch.tensor([0.9, 0.3, 0.1], dtype=torch.float64),
        torch.tensor([0.1, 0.2, 0.7], dtype=torch.float64),
    )
    changed = (out != plain).any(-1)
    assert changed.any()
    interior_writes = (changed & ~touches_background(raster.tri_id)).sum()
    stability.record(6, "welded mesh: pixels written away from the silhouette", interior_writes, 0)
    assert not (changed & ~touches_background(raster.tri_id)).any()
    # Unwelded, the diagonal is an open edge: it gets antialiased (the check can fail).
    cam, verts, faces = square_scene(offset, welded=False)
    raster = ops.rasterize(verts, faces, cam)
    diagonal_pair = (
        (raster.tri_id[:, 1:] != raster.tri_id[:, :-1])
        & (raster.tri_id[:, 1:] >= 0)
        & (raster.tri_id[:, :-1] >= 0)
    )
    assert diagonal_pair.any()
    color = torch.rand(32, 32, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    unwelded = ops.antialias(color, raster, verts, faces, cam)
    inner = ~touches_background(raster.tri_id)
    assert ((unwelded != color).any(-1) & inner).any()


def test_triangles_crossing_the_near_plane_are_not_antialiased():
    cam = identity_camera(24, 24, focal=30.0, near=0.1)
    verts = torch.tensor(
        [[-0.6, -0.4, 2.0], [0.5, -0.5, 2.0], [0.1, 0.6, -1.0]], dtype=torch.float64
    )
    faces = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    v = verts.clone().requires_grad_(True)
    raster = ops.rasterize(verts, faces, cam)
    assert (raster.tri_id >= 0).any() and (raster.tri_id < 0).any()
    color = torch.rand(24, 24, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = ops.antialias(color, raster, v, faces, cam)
    assert torch.equal(out, color)
    (g,) = torch.autograd.grad(out.sum(), v)
    assert (g == 0).all()


def _coverage_error(verts, faces, cam, supersample=8):
    """Mean |antialiased coverage − box-filtered coverage| over pixels the two disagree
    about being fully covered or empty (the silhouette band), for a white mesh on black."""
    raster = ops.rasterize(verts, faces, cam)
    white = (raster.tri_id >= 0).to(verts.dtype)[..., None].contiguous()
    alpha = ops.antialias(white, raster, verts, faces, cam)[..., 0]
    big = cam.resized(cam.width * supersample, cam.height * supersample)
    fine = (ops.rasterize(verts, faces, big).tri_id >= 0).to(verts.dtype)
    truth = torch.nn.functional.avg_pool2d(fine[None, None], supersample)[0, 0]
    band = (truth > 0) & (truth < 1)
    return float((alpha - truth)[band].abs().mean()), int(band.sum())


def test_silhouettes_of_fine_meshes_get_their_coverage():
    """Near a silhouette a finely tessellated surface is seen edge-on: the segment between
    two pixel centres crosses several sliver triangles, and the nearer pixel's own
    triangle rarely holds the silhouette edge. The edge is found by following the segment
    across non-silhouette edges, so the coverage stays close to the true (box-filtered)
    one however fine the mesh (error 0.03 on both spheres); nvdiffrast's rule (the first
    triangle only) leaves much of the silhouette hard (0.12 coarse, 0.21 fine)."""
    coarse = uv_sphere(10, 14, radius=1.0, jitter=0.0, seed=1)[:2]
    fine = uv_sphere(60, 90, radius=1.0, jitter=0.0, seed=1)[:2]
    cam = camera(width=48, height=40, eye=(0.3, 0.2, -3.0))
    err_coarse, n_coarse = _coverage_error(*coarse, cam)
    err_fine, n_fine = _coverage_error(*fine, cam)
    assert n_coarse > 50 and n_fine > 50
    assert err_coarse < 0.05
    assert err_fine < 0.05


def test_interior_pixel_pairs_are_never_blended():
    """A pair whose segment leaves the surface through no silhouette edge within its
    length is not blended: the fine sphere's interior pixel pairs never are."""
    verts, faces = uv_sphere(60, 90, radius=1.0, jitter=0.0, seed=1)[:2]
    cam = camera(width=48, height=40, eye=(0.3, 0.2, -3.0))
    raster = ops.rasterize(verts, faces, cam)
    g = torch.Generator().manual_seed(3)
    color = torch.rand(cam.height, cam.width, 3, dtype=torch.float64, generator=g)
    out = ops.antialias(color, raster, verts, faces, cam)
    covered = raster.tri_id >= 0
    # Interior: the pixel and its four neighbours all covered, two pixels from any edge.
    inner = covered.clone()
    for _ in range(2):
        inner[1:-1, 1:-1] &= inner[:-2, 1:-1] & inner[2:, 1:-1] & inner[1:-1, :-2] & inner[1:-1, 2:]
        inner[0], inner[-1], inner[:, 0], inner[:, -1] = False, False, False, False
    assert inner.sum() > 200
    assert torch.equal(out[inner], color[inner])
