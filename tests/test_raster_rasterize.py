"""urhead.ops.rasterize against the brute-force reference, finite differences, and the
NUMERICS.md mesh cases 1–5."""

import pytest
import torch

from raster_meshes import at_pixel, camera, grid, identity_camera, uv_sphere
from urhead import ops
from urhead.errors import InvalidArgumentError, ShapeError
from urhead.ops import _reference as ref
from urhead.ops._bridge import native


def rel_err(a, b):
    return float((a - b).norm() / b.norm())


def bary_loss(verts, faces, cam, weights):
    return (ops.rasterize(verts, faces, cam).bary * weights).sum()


CAMERAS = [
    dict(eye=(0.3, 0.2, -3.0)),
    dict(eye=(2.5, -1.0, 1.5), fov=30.0),
    dict(eye=(0.0, 0.0, -1.6), fov=70.0),
]


@pytest.mark.parametrize("cam_args", CAMERAS)
def test_forward_matches_reference_float64(cam_args):
    verts, faces, _, _ = uv_sphere(10, 14, jitter=0.05, seed=1)
    cam = camera(**cam_args)
    out, expected = ops.rasterize(verts, faces, cam), ref.rasterize(verts, faces, cam)
    assert torch.equal(out.tri_id, expected.tri_id)
    covered = out.tri_id >= 0
    assert covered.sum() > 300
    assert (out.bary - expected.bary).abs().max() < 1e-12
    assert (out.depth[covered] - expected.depth[covered]).abs().max() < 1e-12
    assert torch.isinf(out.depth[~covered]).all() and (out.bary[~covered] == 0).all()


def test_forward_float32_agrees_with_float64_reference():
    verts, faces, _, _ = uv_sphere(10, 14, jitter=0.05, seed=2)
    cam = camera(eye=(0.5, 0.4, -2.8))
    out = ops.rasterize(verts.float(), faces, cam)
    expected = ref.rasterize(verts.float().double(), faces, cam)
    assert torch.equal(out.tri_id, expected.tri_id)
    assert out.bary.dtype == torch.float32
    assert (out.bary.double() - expected.bary).abs().max() < 1e-6
    covered = out.tri_id >= 0
    assert (out.depth.double() - expected.depth)[covered].abs().max() < 1e-6


@pytest.mark.parametrize("cam_args", CAMERAS)
def test_gradient_matches_reference(cam_args):
    verts, faces, _, _ = uv_sphere(10, 14, jitter=0.05, seed=3)
    cam = camera(**cam_args)
    weights = torch.randn(cam.height, cam.width, 2, dtype=torch.float64)
    v = verts.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(bary_loss(v, faces, cam, weights), v)
    (g_ref,) = torch.autograd.grad((ref.rasterize(v, faces, cam).bary * weights).sum(), v)
    assert rel_err(g, g_ref) < 2e-12


def test_gradient_float32_agrees_with_float64_reference():
    verts, faces, _, _ = uv_sphere(10, 14, jitter=0.05, seed=4)
    cam = camera()
    weights = torch.randn(cam.height, cam.width, 2, dtype=torch.float64)
    v32 = verts.float().requires_grad_(True)
    (g,) = torch.autograd.grad(bary_loss(v32, faces, cam, weights.float()), v32)
    v64 = verts.float().double().requires_grad_(True)
    (g_ref,) = torch.autograd.grad((ref.rasterize(v64, faces, cam).bary * weights).sum(), v64)
    assert rel_err(g.double(), g_ref) < 2e-6


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_backward_from_the_kept_setup_is_the_backward_that_sets_up_again(dtype):
    """The op's backward reads the triangles' setup its forward kept (a third of the
    backward's time); the native backward without it sets them up again: the same bits.
    A state of another dtype or mesh is refused."""
    verts, faces, _, _ = uv_sphere(12, 16, jitter=0.05, seed=5, dtype=dtype)
    cam = camera(eye=(0.4, -0.3, -2.0), fov=45.0)
    weights = torch.randn(cam.height, cam.width, 2, dtype=dtype)
    v = verts.clone().requires_grad_(True)
    (g_kept,) = torch.autograd.grad(bary_loss(v, faces, cam, weights), v)
    f32 = faces.to(torch.int32).numpy()
    args = (verts.numpy(), f32, cam.core_args())
    *raster, state = native("rasterize_forward")(*args, 2)
    tri_id = raster[0]
    for kept in (None, state):
        again = native("rasterize_backward")(kept, *args, tri_id, weights.numpy(), 1)
        assert torch.equal(torch.from_numpy(again), g_kept)
    other = torch.float64 if dtype == torch.float32 else torch.float32
    *_, other_state = native("rasterize_forward")(verts.to(other).numpy(), f32, cam.core_args(), 1)
    with pytest.raises(InvalidArgumentError, match="dtype"):
        native("rasterize_backward")(other_state, *args, tri_id, weights.numpy(), 1)
    *_, fewer = native("rasterize_forward")(verts.numpy(), f32[:-1], cam.core_args(), 1)
    with pytest.raises(ShapeError, match="setup"):
        native("rasterize_backward")(fewer, *args, tri_id, weights.numpy(), 1)


def directional_check(verts, faces, cam, weights, seed, h=1e-7):
    """Central difference of Σ w·bary along a random direction; coverage must not change."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(verts.shape, generator=g, dtype=torch.float64)
    d /= d.norm()
    v = verts.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(bary_loss(v, faces, cam, weights), v)
    base = ops.rasterize(verts, faces, cam).tri_id
    for s in (h, -h):
        assert torch.equal(ops.rasterize(verts + s * d, faces, cam).tri_id, base)
    fd = (
        bary_loss(verts + h * d, faces, cam, weights)
        - bary_loss(verts - h * d, faces, cam, weights)
    ) / (2 * h)
    return float((grad * d).sum()), float(fd)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradient_matches_finite_differences(seed):
    verts, faces, _, _ = uv_sphere(8, 12, jitter=0.05, seed=seed)
    cam = camera(eye=(0.4 * seed, 0.3, -3.0))
    weights = torch.randn(
        cam.height, cam.width, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)
    )
    an, fd = directional_check(verts, faces, cam, weights, seed)
    assert abs(an - fd) <= 1e-7 * max(1.0, abs(fd))


# --- NUMERICS.md case 1: near plane ------------------------------------------------------


def near_plane_case(behind_z):
    cam = identity_camera(64, 48, focal=60.0, near=0.05)
    # Irregular coordinates: the reference counts centres exactly on an edge as covered
    # (no top-left rule for clipped triangles), so avoid edges through pixel centres.
    verts = torch.tensor(
        [[0.2137, 0.1093, behind_z], [-0.5122, -0.3071, 2.0], [0.6033, -0.4121, 2.5]],
        dtype=torch.float64,
    )
    return cam, verts, torch.tensor([[0, 1, 2]], dtype=torch.int32)


@pytest.mark.parametrize("behind_z", [-0.5, 0.0])
def test_case1_triangle_through_the_near_plane_covers_the_clipped_polygon(behind_z, stability):
    cam, verts, faces = near_plane_case(behind_z)
    out = ops.rasterize(verts, faces, cam)
    expected = ref.rasterize(verts, faces, cam)  # exact ray/plane coverage with z ≥ near
    covered = out.tri_id >= 0
    assert covered.sum() > 200
    # Snapped and exact coverage could differ only within a sub-pixel step of an edge;
    # for this geometry they agree.
    mismatched = (out.tri_id != expected.tri_id).sum()
    stability.record(1, "through near: pixels whose coverage differs from the clip", mismatched, 0)
    assert torch.equal(out.tri_id, expected.tri_id)
    both = covered & (expected.tri_id >= 0)
    bary_err = (out.bary - expected.bary)[both].abs().max()
    stability.record(1, "through near: max abs barycentric error vs float64 clip", bary_err, 1e-13)
    assert bary_err < 1e-13
    assert (out.depth[covered] >= cam.near * (1 - 1e-9)).all()
    assert torch.isfinite(out.bary).all()
    v = verts.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(ops.rasterize(v, faces, cam).bary.sum(), v)
    (g_ref,) = torch.autograd.grad((ref.rasterize(v, faces, cam).bary * both[..., None]).sum(), v)
    assert torch.isfinite(g).all()
    stability.record(
        1, "through near: relative L2 error of the vertex gradient", rel_err(g, g_ref), 1e-12
    )
    assert rel_err(g, g_ref) < 1e-12


def test_case1_triangle_fully_behind_the_camera_is_culled(stability):
    cam, verts, faces = near_plane_case(-0.5)
    verts[:, 2] = torch.tensor([-0.5, -2.0, -1e-9])
    v = verts.clone().requires_grad_(True)
    out = ops.rasterize(v, faces, cam)
    assert (out.tri_id == -1).all()
    (g,) = torch.autograd.grad(out.bary.sum(), v, allow_unused=True)
    assert g is None or (g == 0).all()
    stability.checked(1, "fully behind (z = −1e-9 … −2): culled, zero gradient")


def test_case1_huge_triangle_through_the_near_plane_covers_the_screen(stability):
    cam = identity_camera(32, 32, focal=40.0, near=0.01)
    verts = torch.tensor(
        [[-1e4, -1e4, 2.0], [1e4, -1e4, 2.0], [0.0, 1e4, -1.0]], dtype=torch.float64
    )
    faces = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    out, expected = ops.rasterize(verts, faces, cam), ref.rasterize(verts, faces, cam)
    assert torch.equal(out.tri_id, expected.tri_id)
    # Far beyond the guard band on two vertices, behind the camera on the third.
    assert (out.tri_id == 0).all()
    bary_err = (out.bary - expected.bary).abs().max()
    stability.record(1, "huge (1e4) through near: max abs barycentric error", bary_err, 1e-9)
    assert bary_err < 1e-9
    assert torch.isfinite(out.bary).all()


def test_pixels_beyond_the_far_plane_stay_empty():
    cam = identity_camera(32, 24, focal=30.0, near=0.01, far=2.0)
    verts = torch.tensor(
        [[-1.5, -1.0, 1.0], [1.5, -1.0, 3.0], [0.0, 1.5, 2.0]], dtype=torch.float64
    )
    faces = torch.tensor([[0, 1, 2]], dtype=torch.int32)
    out, expected = ops.rasterize(verts, faces, cam), ref.rasterize(verts, faces, cam)
    covered = out.tri_id >= 0
    assert torch.equal(out.tri_id, expected.tri_id)
    assert covered.any() and (out.depth[covered] <= 2.0).all()
    far_away = ops.rasterize(verts, faces, identity_camera(32, 24, focal=30.0, far=100.0))
    assert ((far_away.tri_id >= 0) & ~covered).any()  # the far plane did cut pixels


# --- NUMERICS.md case 2: degenerate triangles ---------------------------------------------


def test_case2_degenerate_triangles_cover_nothing_and_stay_finite(stability):
    cam = identity_camera(32, 32, focal=40.0)
    p = lambda x, y, z=2.0: at_pixel(cam, x, y, z)  # noqa: E731
    verts = torch.stack(
        [
            p(5.3, 5.1),
            p(20.7, 9.2),
            p(12.1, 25.9),  # a healthy triangle: 0, 1, 2
            p(3.0, 3.0),
            p(9.0, 9.0),
            p(15.0, 15.0),  # collinear: 3, 4, 5
            p(10.0, 10.0),
            p(10.0 + 1e-6, 10.0),
            p(10.0, 10.0 + 1e-6),  # 1e-12 px²: 6, 7, 8
            torch.tensor([0.0, 0.0, 1.0]),
            torch.tensor([0.0, 0.0, 3.0]),  # edge-on, with 0: 9, 10
        ]
    )
    verts = torch.cat([verts, torch.tensor([[0.0, 0.5, 2.0]], dtype=torch.float64)])  # 11
    faces = torch.tensor(
        [[0, 0, 1], [3, 4, 5], [6, 7, 8], [9, 10, 11], [1, 1, 1]], dtype=torch.int32
    )
    v = verts.clone().requires_grad_(True)
    out = ops.rasterize(v, faces, cam)
    stability.record(2, "pixels covered by a degenerate triangle", (out.tri_id != -1).sum(), 0)
    assert (out.tri_id == -1).all()
    (g,) = torch.autograd.grad((out.bary * 1.0).sum(), v, allow_unused=True)
    assert g is None or torch.isfinite(g).all()
    # Adding a healthy triangle: it alone is drawn.
    faces = torch.cat([faces, torch.tensor([[0, 1, 2]], dtype=torch.int32)])
    out = ops.rasterize(verts, faces, cam)
    assert set(out.tri_id.unique().tolist()) == {-1, 5}
    assert torch.isfinite(out.bary).all() and torch.isfinite(out.depth[out.tri_id >= 0]).all()
    stability.checked(
        2, "5 degenerate triangles: no coverage, finite gradient; healthy one drawn", 5
    )


# --- NUMERICS.md case 3: sliver -----------------------------------------------------------


def sliver(cam, y_apex, y_b, y_c, dtype=torch.float64):
    verts = torch.stack(
        [
            at_pixel(cam, 0.5, y_apex, 0.01),
            at_pixel(cam, 1000.5, y_b, 1e4),
            at_pixel(cam, 1000.5, y_c, 1e4),
        ]
    ).to(dtype)
    return verts, torch.tensor([[0, 1, 2]], dtype=torch.int32)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case3_sliver_barycentrics_sum_to_one_and_match_finite_differences(dtype, stability):
    # 1000 px long, 1e-3 px wide, depths (0.01, 1e4, 1e4). Its two long edges straddle a
    # sub-pixel rounding boundary, so the snapped sliver keeps one sub-pixel step of width
    # and its top edge runs through the pixel centres of row 8 (top-left rule: covered).
    cam = identity_camera(1008, 16, focal=500.0, cx=504.0, cy=8.0, near=0.01, far=1e5)
    mid = 8.5 + 1 / 512
    verts, faces = sliver(cam, mid - 1e-4, mid - 5e-4, mid + 5e-4, dtype)
    out = ops.rasterize(verts, faces, cam)
    covered = out.tri_id >= 0
    assert covered.sum() >= 900 and covered[8].sum() == covered.sum()
    b = out.bary[covered].double()
    total = 1 - b.sum(-1) + b.sum(-1)  # the implicit first weight closes the sum
    assert torch.isfinite(b).all() and (b >= 0).all() and (b.sum(-1) <= 1 + 1e-6).all()
    sum_err = max(float((b.sum(-1) - 1).clamp_min(0).max()), float((total - 1).abs().max()))
    stability.record(3, f"barycentric sum − 1 ({str(dtype)[6:]})", sum_err, 1e-6)
    assert ((total - 1).abs() < 1e-6).all()
    depth = out.depth[covered].double()
    assert (depth >= 0.01 * (1 - 1e-6)).all() and (depth <= 1e4 * (1 + 1e-6)).all()
    if dtype == torch.float64:
        expected = ref.rasterize(verts, faces, cam)
        assert torch.equal(out.tri_id, expected.tri_id)
        bary_err = (out.bary - expected.bary).abs().max()
        stability.record(3, "max abs barycentric error vs float64 reference", bary_err, 1e-14)
        assert bary_err < 1e-14
        weights = torch.randn(
            16, 1008, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(5)
        )
        an, fd = directional_check(verts, faces, cam, weights, seed=6, h=1e-9)
        fd_err = abs(an - fd) / max(1.0, abs(fd))
        stability.record(3, "directional gradient vs float64 central differences", fd_err, 5e-7)
        assert abs(an - fd) <= 5e-7 * max(1.0, abs(fd))


def test_case3_sliver_thinner_than_a_subpixel_step_is_dropped():
    cam = identity_camera(1008, 16, focal=500.0, cx=504.0, cy=8.0, near=0.01, far=1e5)
    verts, faces = sliver(cam, 8.5, 8.5 - 5e-4, 8.5 + 5e-4)  # snaps to zero area
    out = ops.rasterize(verts, faces, cam)
    assert (out.tri_id == -1).all()


# --- NUMERICS.md case 4 (perspective): watertight ---------------------------------------


@pytest.mark.parametrize("jitter", [0.0, 0.3])
def test_case4_watertight_perspective_grid(jitter, stability):
    # A 17 × 17 vertex grid on a tilted plane; with jitter 0 every vertex projects onto a
    # pixel centre (the hardest case for the top-left rule).
    cam = identity_camera(40, 40, focal=50.0)
    n = 17
    g = torch.Generator().manual_seed(3)
    pts = []
    for i in range(n):
        for j in range(n):
            x = 4.5 + 2 * j + jitter * float(torch.rand(1, generator=g))
            y = 3.5 + 2 * i + jitter * float(torch.rand(1, generator=g))
            pts.append(at_pixel(cam, x, y, 2.0 + 0.05 * i + 0.03 * j))
    verts = torch.stack(pts)
    faces, classes = grid(n)
    count = torch.zeros(40, 40, dtype=torch.int64)
    for c in range(8):
        count += ops.rasterize(verts, faces[classes == c], cam).tri_id >= 0
    whole = ops.rasterize(verts, faces, cam).tri_id >= 0
    interior = count[5:34, 6:35]
    wrong = int((count > 1).sum() + (interior != 1).sum())
    stability.record(4, "perspective grid: pixels covered 0 or ≥ 2 times", wrong, 0)
    assert count.max() == 1
    assert torch.equal(count == 1, whole)
    assert count[5:34, 6:35].min() == 1  # every pixel strictly inside the grid


# --- NUMERICS.md case 5: depth ties -------------------------------------------------------


@pytest.mark.parametrize("z", [1.0, 10.0, 50.0])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case5_nearer_plane_wins_and_ties_go_to_the_lower_id(z, dtype, stability):
    cam = identity_camera(24, 24, focal=30.0, far=100.0)

    def quad(depth, tilt):
        corners = [(2.2, 2.7), (21.6, 2.3), (21.9, 21.4), (2.5, 21.8)]
        return torch.stack([at_pixel(cam, x, y, depth + tilt * (x - 12.0)) for x, y in corners]).to(
            dtype
        )

    for tilt in (0.0, 1e-2):
        far_q, near_q = quad(z + 1e-3, tilt), quad(z, tilt)
        verts = torch.cat([far_q, near_q, near_q])  # 0–3 far, 4–7 near, 8–11 near again
        q = lambda o: [[o, o + 1, o + 2], [o, o + 2, o + 3]]  # noqa: E731
        for order in ([0, 4, 8], [8, 4, 0], [4, 0, 8]):
            faces = torch.tensor([t for o in order for t in q(o)], dtype=torch.int32)
            out = ops.rasterize(verts, faces, cam)
            covered = out.tri_id >= 0
            assert covered.sum() > 300
            slot = {o: 2 * i for i, o in enumerate(order)}
            # The near quad wins everywhere; between its two identical copies, the lower ids.
            winners = torch.tensor(sorted([slot[4], slot[8]]))
            ids = out.tri_id[covered]
            lost = ((ids // 2) * 2 != winners[0]).sum()
            stability.record(5, "pixels not won by the nearer plane's lowest copy", lost, 0)
            assert ((ids // 2) * 2 == winners[0]).all(), (z, tilt, order)
