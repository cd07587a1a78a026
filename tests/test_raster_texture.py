"""urhead.ops.texture against the reference and finite differences, the sparse gradient
contract, and NUMERICS.md cases 7 and 8."""

import math

import pytest
import torch

from raster_meshes import identity_camera
from urhead import ops
from urhead.ops import _reference as ref

SIZES = [(1, 1), (3, 5), (16, 16), (7, 2)]


def random_case(size, channels=4, n=200, dtype=torch.float64, seed=0, spread=(-0.2, 1.2)):
    g = torch.Generator().manual_seed(seed)
    tex = torch.randn(*size, channels, generator=g, dtype=torch.float64).to(dtype)
    uv = spread[0] + (spread[1] - spread[0]) * torch.rand(n, 2, generator=g, dtype=torch.float64)
    return tex, uv.to(dtype)


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_matches_reference(size, dtype):
    tex, uv = random_case(size, dtype=dtype)
    out = ops.texture(tex, uv)
    expected = ref.texture(tex.double(), uv.double())
    assert out.shape == (200, 4) and out.dtype == dtype
    assert (out.double() - expected).abs().max() < (5e-6 if dtype == torch.float32 else 1e-14)


def test_leading_dimensions_are_kept():
    tex, uv = random_case((8, 8), n=60)
    out = ops.texture(tex, uv.reshape(3, 4, 5, 2))
    assert out.shape == (3, 4, 5, 4)
    assert torch.equal(out.reshape(60, 4), ops.texture(tex, uv))


@pytest.mark.parametrize("size", SIZES)
def test_gradients_match_reference(size):
    tex, uv = random_case(size, seed=1)
    tex.requires_grad_(True)
    uv.requires_grad_(True)
    weights = torch.randn(200, 4, dtype=torch.float64)
    g_tex, g_uv = torch.autograd.grad((ops.texture(tex, uv) * weights).sum(), (tex, uv))
    e_tex, e_uv = torch.autograd.grad((ref.texture(tex, uv) * weights).sum(), (tex, uv))
    assert g_tex.is_sparse
    assert (g_tex.to_dense() - e_tex).abs().max() < 1e-13
    assert (g_uv - e_uv).abs().max() < 1e-14 * max(1.0, float(e_uv.abs().max()))


def test_float32_gradients_agree_with_float64():
    tex, uv = random_case((16, 16), seed=2)
    weights = torch.randn(200, 4, dtype=torch.float64)

    def grads(dtype):
        t = tex.to(dtype).requires_grad_(True)
        u = uv.to(dtype).requires_grad_(True)
        return torch.autograd.grad((ops.texture(t, u) * weights.to(dtype)).sum(), (t, u))

    (t32, u32), (t64, u64) = grads(torch.float32), grads(torch.float64)
    d32, d64 = t32.to_dense().double(), t64.to_dense()
    assert ((d32 - d64).norm() / d64.norm()) < 1e-6
    assert ((u32.double() - u64).norm() / u64.norm()) < 2e-6


def test_gradcheck_uv_and_tex():
    tex, uv = random_case((5, 6), channels=2, n=30, seed=3, spread=(0.05, 0.95))
    tex.requires_grad_(True)
    uv.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t, u: ops.texture(t, u, sparse_grad=False), (tex, uv))


def test_sparse_gradient_contract():
    tex, uv = random_case((32, 24), channels=3, n=500, seed=4, spread=(0.1, 0.6))
    tex.requires_grad_(True)
    (g,) = torch.autograd.grad(ops.texture(tex, uv).sum(), tex)
    assert g.is_sparse and g.is_coalesced() and g.shape == tex.shape
    assert g.sparse_dim() == 2 and g.dense_dim() == 1
    idx = g._indices()
    assert idx.dtype == torch.int64 and g._values().shape == (idx.shape[1], 3)
    flat = idx[0] * 24 + idx[1]
    assert (flat[1:] > flat[:-1]).all()  # sorted, unique
    # .backward() accumulation keeps the data (torch drops only the coalesced flag).
    ops.texture(tex, uv).sum().backward()
    assert torch.equal(tex.grad._indices(), idx) and torch.equal(tex.grad._values(), g._values())
    # Exactly the texels with a non-zero bilinear weight, and their values.
    t = tex.detach().clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(ref.texture(t, uv).sum(), t)
    assert torch.equal(g.to_dense() != 0, expected != 0)
    assert (g.to_dense() - expected).abs().max() < 1e-13


def test_sparse_adam_consumes_the_gradient_and_touches_only_listed_texels():
    tex, uv = random_case((32, 32), channels=3, n=100, seed=5, spread=(0.2, 0.4))
    param = torch.nn.Parameter(tex.clone())
    opt = torch.optim.SparseAdam([param], lr=0.1)
    ops.texture(param, uv).square().sum().backward()
    listed = param.grad.to_dense().abs().sum(-1) != 0
    opt.step()
    changed = (param.detach() != tex).any(-1)
    assert changed.any()
    assert torch.equal(changed, listed)


def test_zero_output_gradient_lists_no_texels():
    tex, uv = random_case((8, 8), n=50)
    tex.requires_grad_(True)
    out = ops.texture(tex, uv)
    (out * 0).sum().backward()
    assert tex.grad._nnz() == 0


def test_dense_gradient_option():
    tex, uv = random_case((4, 4), n=20)
    tex.requires_grad_(True)
    ops.texture(tex, uv, sparse_grad=False).sum().backward()
    assert tex.grad.layout == torch.strided


# --- NUMERICS.md case 7 -------------------------------------------------------------------

SPECIAL = [-1e-7, 0.0, 1.0, 1.0 + 1e-7, 1e20, -1e20, math.inf, -math.inf, math.nan, 0.5]


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (4, 4)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case7_special_coordinates(size, dtype, stability):
    ht, wt = size
    centres_u = [(c + 0.5) / wt for c in range(wt)]
    values = SPECIAL + centres_u
    uv = torch.tensor([[u, v] for u in values for v in values], dtype=dtype)
    finite = torch.isfinite(uv).all(-1)
    # Weights sum to 1: a constant texture samples to that constant wherever uv is finite.
    ones = torch.ones(ht, wt, 2, dtype=dtype)
    out = ops.texture(ones, uv)
    weight_err = (out[finite] - 1).abs().max()
    stability.record(7, "weights sum − 1 at special and centre coordinates", weight_err, 0)
    assert torch.equal(out[finite], torch.ones_like(out[finite]))
    assert torch.equal(out[~finite], torch.zeros_like(out[~finite]))
    # Against the reference (clamp-to-edge), and the documented zeros for non-finite uv.
    tex = torch.randn(ht, wt, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    t = tex.to(dtype).requires_grad_(True)
    u = uv.clone().requires_grad_(True)
    out = ops.texture(t, u)
    expected = ref.texture(tex, uv.double())
    err = (out.double() - expected).abs().max()
    tol = 1e-6 if dtype == torch.float32 else 1e-15
    stability.record(7, f"max abs error vs float64 reference ({str(dtype)[6:]})", err, tol)
    assert (out.double() - expected).abs().max() < (1e-6 if dtype == torch.float32 else 1e-15)
    g_tex, g_uv = torch.autograd.grad(out.sum(), (t, u))
    assert torch.isfinite(g_uv).all() and torch.isfinite(g_tex._values()).all()
    stability.record(7, "max |UV gradient| at non-finite UV", g_uv[~finite].abs().max(), 0)
    assert (g_uv[~finite] == 0).all()
    # Clamped coordinates (beyond the outer texel centres) pass no UV gradient.
    u_out = (uv[:, 0] < 0.5 / wt) | (uv[:, 0] > 1 - 0.5 / wt)
    v_out = (uv[:, 1] < 0.5 / ht) | (uv[:, 1] > 1 - 0.5 / ht)
    assert (g_uv[finite & u_out, 0] == 0).all() and (g_uv[finite & v_out, 1] == 0).all()
    # Texel centres sample exactly that texel.
    centre_uv = torch.tensor(
        [[(c + 0.5) / wt, 1 - (r + 0.5) / ht] for r in range(ht) for c in range(wt)], dtype=dtype
    )
    # (up to the rounding of the centre coordinate itself).
    at_centres = ops.texture(tex.to(dtype), centre_uv).double()
    tol = 1e-6 if dtype == torch.float32 else 1e-15
    centre_err = (at_centres - tex.reshape(-1, 2)).abs().max()
    stability.record(7, f"texel centre sample − texel ({str(dtype)[6:]})", centre_err, tol)
    assert (at_centres - tex.reshape(-1, 2)).abs().max() < tol


def test_case7_texture_gradient_total_weight_is_one_per_finite_sample(stability):
    tex = torch.zeros(3, 5, 1, dtype=torch.float64, requires_grad=True)
    uv = torch.tensor([[u, v] for u in SPECIAL for v in SPECIAL], dtype=torch.float64)
    ops.texture(tex, uv).sum().backward()
    finite = torch.isfinite(uv).all(-1).sum()
    total_err = abs(float(tex.grad._values().sum()) - float(finite))
    stability.record(
        7, "texel-gradient weight summed over samples − sample count", total_err, 1e-12
    )
    assert abs(float(tex.grad._values().sum()) - float(finite)) < 1e-12
    assert (tex.grad._values() >= 0).all()


# --- NUMERICS.md case 8 -------------------------------------------------------------------


def test_case8_texels_outside_two_uv_islands_get_exactly_zero_gradient(stability):
    # Two quads side by side on screen; their UV faces map to two separate islands.
    cam = identity_camera(48, 24, focal=40.0)
    z = 2.0
    xs = [-1.1, -0.1, 0.1, 1.1]
    verts = torch.tensor(
        [[x, y, z] for x in xs for y in (-0.5, 0.5)], dtype=torch.float64
    )  # ids: x-major, y-minor
    faces = torch.tensor([[0, 2, 3], [0, 3, 1], [4, 6, 7], [4, 7, 5]], dtype=torch.int32)
    islands = [(0.1, 0.35, 0.2, 0.8), (0.6, 0.9, 0.1, 0.4)]  # u0, u1, v0, v1
    uv_coords = torch.tensor(
        [[u, v] for (u0, u1, v0, v1) in islands for u in (u0, u1) for v in (v0, v1)],
        dtype=torch.float64,
    )
    raster = ops.rasterize(verts, faces, cam)
    assert (raster.tri_id >= 0).sum() > 200
    uv = ops.interpolate(uv_coords, raster, faces)
    tex = torch.nn.Parameter(torch.randn(64, 64, 3, dtype=torch.float64))
    color = ops.texture(tex, uv)
    covered = (raster.tri_id >= 0)[..., None]
    (color * covered).square().sum().backward()
    g = tex.grad.to_dense().abs().sum(-1)
    # Texel (r, c) is inside an island's bilinear footprint if its centre is within one
    # texel of the island's UV rectangle.
    r = torch.arange(64, dtype=torch.float64)[:, None]
    c = torch.arange(64, dtype=torch.float64)[None, :]
    u_c, v_c = (c + 0.5) / 64, 1 - (r + 0.5) / 64
    near_island = torch.zeros(64, 64, dtype=torch.bool)
    for u0, u1, v0, v1 in islands:
        near_island |= (
            (u_c > u0 - 1 / 64) & (u_c < u1 + 1 / 64) & (v_c > v0 - 1 / 64) & (v_c < v1 + 1 / 64)
        )
    stability.record(8, "max |gradient| on texels outside both islands", g[~near_island].max(), 0)
    assert (g[~near_island] == 0).all()
    assert (g[near_island] != 0).float().mean() > 0.5
    listed = torch.zeros(64, 64, dtype=torch.bool)
    listed[tex.grad._indices()[0], tex.grad._indices()[1]] = True
    assert not (listed & ~near_island).any()
    stability.record(
        8,
        "texels outside the islands listed in the sparse gradient",
        (listed & ~near_island).sum(),
        0,
    )
