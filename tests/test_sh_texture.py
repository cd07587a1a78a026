"""sh_texture: the fused lookup + SH shading against its plain-torch reference (float64 values
and both gradients), finite differences, the lookup-then-shade path it replaces (bit for bit
in float32, values and the texture's per-sample gradient), special coordinates (NUMERICS.md
case 7), threads, bad input, a TextureGather, and the avatar's mesh branch with shading maps."""

from __future__ import annotations

import math

import pytest
import torch

import urhead.model.avatar
from test_model import camera, make_avatar
from urhead.errors import DTypeError, InvalidArgumentError, NonFiniteError, ShapeError
from urhead.head import procedural_head
from urhead.model.map_layout import MapLayout
from urhead.ops import TextureGather, _reference, sh_shade, sh_texture, texture

F64 = torch.float64
CHANNELS = 56  # the paper's layout: 48 SH colour, normal 48:51, then 5 more
NORMAL = slice(48, 51)


def _case(n=300, size=(9, 7), dtype=F64, seed=0, spread=(-0.1, 1.1)):
    """A texture, UVs over it and a little beyond, unit directions."""
    g = torch.Generator().manual_seed(seed)
    tex = torch.randn(*size, CHANNELS, generator=g, dtype=F64) * 0.5
    uv = spread[0] + (spread[1] - spread[0]) * torch.rand(n, 2, generator=g, dtype=F64)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=1)
    return tex.to(dtype), uv.to(dtype), dirs.to(dtype)


def _joined(fn):
    """``fn`` (the op or its reference) with its two parts joined: (P, 3 + E)."""
    return lambda *args, **kwargs: torch.cat(fn(*args, **kwargs), 1)


def _recorded(gather: TextureGather) -> tuple[torch.Tensor, torch.Tensor]:
    """The gather's recorded lookups joined: (uv (M, 2), v_out (M, C))."""
    uv, v_out = zip(*gather.samples(), strict=True)
    return torch.cat(uv), torch.cat(v_out)


def _run(fn, tex, uv, dirs, degree, extra, weights):
    """Values and the gradients of Σ w·values to tex (dense) and uv."""
    t = tex.clone().requires_grad_(True)
    u = uv.clone().requires_grad_(True)
    out = fn(t, u, dirs, degree, extra)
    (out * weights).sum().backward()
    g_tex = t.grad.to_dense() if t.grad.is_sparse else t.grad
    return out.detach(), g_tex, u.grad


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("extra", [None, NORMAL, slice(48, 56)])
def test_matches_reference_float64(degree, extra):
    tex, uv, dirs = _case(seed=degree)
    width = 3 + (0 if extra is None else extra.stop - extra.start)
    weights = torch.randn(300, width, generator=torch.Generator().manual_seed(1), dtype=F64)
    ours = _run(_joined(sh_texture), tex, uv, dirs, degree, extra, weights)
    ref = _run(_joined(_reference.sh_texture), tex, uv, dirs, degree, extra, weights)
    assert ours[0].shape == (300, width)
    for a, b in zip(ours, ref, strict=True):
        assert (a - b).abs().max() <= 1e-13 * (1 + b.abs().max())


@pytest.mark.parametrize("used", ["rgb", "extra"])
def test_a_part_the_loss_does_not_use_is_a_zero_gradient(used):
    """The colour and the extra channels are two outputs: a loss of one of them sends the
    backward no gradient for the other (None), which must act as zeros, bit for bit."""
    tex, uv, dirs = _case(seed=4, dtype=torch.float32)
    weights = torch.randn(300, 6, generator=torch.Generator().manual_seed(2))
    part = slice(0, 3) if used == "rgb" else slice(3, 6)
    zeroed = torch.zeros_like(weights)
    zeroed[:, part] = weights[:, part]

    def one_part(t, u, dirs, degree, extra):
        rgb, extra_values = sh_texture(t, u, dirs, degree, extra)
        return rgb if used == "rgb" else extra_values

    _, g_tex, g_uv = _run(one_part, tex, uv, dirs, 3, NORMAL, weights[:, part])
    _, g_tex0, g_uv0 = _run(_joined(sh_texture), tex, uv, dirs, 3, NORMAL, zeroed)
    assert torch.equal(g_tex, g_tex0) and torch.equal(g_uv, g_uv0)
    assert g_uv.ne(0).any()


def test_gradcheck_uv_float64():
    tex, uv, dirs = _case(n=40, size=(5, 4), seed=2, spread=(0.1, 0.9))
    u = uv.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda u: _joined(sh_texture)(tex, u, dirs, 3, NORMAL), (u,))


def test_float32_is_the_lookup_then_shading_bit_for_bit():
    """Values and the texture's per-sample gradient (what a TextureGather records) equal
    those of ``texture`` + ``sh_shade`` + a slice exactly; the UV gradient to rounding."""
    tex, uv, dirs = _case(n=5000, size=(64, 48), dtype=torch.float32, seed=3)
    weights = torch.randn(5000, 6, generator=torch.Generator().manual_seed(4))
    results = []
    for fused in (True, False):
        maps = tex.clone().requires_grad_(True)
        gather = TextureGather(maps)
        u = uv.clone().requires_grad_(True)
        if fused:
            out = _joined(sh_texture)(maps, u, dirs, 3, NORMAL, gather=gather)
        else:
            rows = gather.sample(u)
            out = torch.cat([sh_shade(rows, dirs, 3), rows[:, NORMAL]], 1)
        (out * weights).sum().backward()
        results.append((out.detach(), *_recorded(gather), u.grad))
    (out, s_uv, s_rows, g_uv), (out0, s_uv0, s_rows0, g_uv0) = results
    assert torch.equal(out, out0) and torch.equal(s_uv, s_uv0) and torch.equal(s_rows, s_rows0)
    assert torch.allclose(g_uv, g_uv0, rtol=1e-4, atol=1e-4 * g_uv0.abs().max())


@pytest.mark.parametrize("size", [(1, 1), (3, 5)])
def test_case7_special_coordinates(size, stability):
    """Non-finite coordinates read zeros (colour 0.5) and pass no UV gradient; clamped ones
    pass none along their axis; values agree with the reference everywhere."""
    ht, wt = size
    special = [-1e-7, 0.0, 1.0, 1.0 + 1e-7, 1e20, -1e20, math.inf, -math.inf, math.nan, 0.5]
    uv = torch.tensor([[u, v] for u in special for v in special], dtype=F64)
    finite = torch.isfinite(uv).all(-1)
    tex, _, _ = _case(size=size, seed=5)
    dirs = torch.nn.functional.normalize(torch.ones(len(uv), 3, dtype=F64), dim=1)
    weights = torch.ones(len(uv), 6, dtype=F64)
    out, g_tex, g_uv = _run(_joined(sh_texture), tex, uv, dirs, 3, NORMAL, weights)
    expected = _joined(_reference.sh_texture)(tex, uv, dirs, 3, NORMAL)
    stability.record(
        7, "sh_texture: max abs error vs float64 reference", (out - expected).abs().max(), 1e-14
    )
    assert torch.equal(out[~finite, :3], torch.full_like(out[~finite, :3], 0.5))
    assert out[~finite, 3:].eq(0).all() and torch.isfinite(g_tex).all()
    stability.record(
        7, "sh_texture: max |UV gradient| at non-finite UV", g_uv[~finite].abs().max(), 0
    )
    u_out = (uv[:, 0] < 0.5 / wt) | (uv[:, 0] > 1 - 0.5 / wt)
    v_out = (uv[:, 1] < 0.5 / ht) | (uv[:, 1] > 1 - 0.5 / ht)
    assert (g_uv[finite & u_out, 0] == 0).all() and (g_uv[finite & v_out, 1] == 0).all()


def test_clamped_colour_passes_no_gradient():
    tex = torch.zeros(2, 2, CHANNELS, dtype=F64)
    tex[..., 0] = -10.0  # red's DC term: far below 0 everywhere
    tex[0, 0, 48] = 1.0
    uv = torch.tensor([[0.3, 0.6], [0.7, 0.2]], dtype=F64)
    dirs = torch.tensor([[0.0, 0.0, 1.0]] * 2, dtype=F64)
    out, g_tex, g_uv = _run(
        _joined(sh_texture), tex, uv, dirs, 0, NORMAL, torch.ones(2, 6, dtype=F64)
    )
    assert out[:, 0].eq(0).all() and out[:, 1:3].eq(0.5).all()
    assert g_tex[..., 0].eq(0).all() and g_tex[..., 1].ne(0).any()
    # Only the normal's channel 48 varies, so it alone moves the UV gradient.
    assert torch.allclose(
        g_uv, _run(lambda t, u, *_: texture(t, u)[:, 48:49], tex, uv, dirs, 0, None, 1.0)[2]
    )


def test_only_the_requested_gradients_and_no_graph_without_them():
    tex, uv, dirs = _case(n=50, dtype=torch.float32, seed=6)
    t = tex.clone().requires_grad_(True)
    out = _joined(sh_texture)(t, uv, dirs, 2, NORMAL)
    out.sum().backward()
    assert t.grad.is_sparse and t.grad.shape == tex.shape
    u = uv.clone().requires_grad_(True)
    _joined(sh_texture)(tex, u, dirs, 2).sum().backward()
    assert u.grad.shape == (50, 2)
    assert not _joined(sh_texture)(tex, uv, dirs, 2).requires_grad


def test_same_bits_for_any_thread_count(monkeypatch, stability):
    tex, uv, dirs = _case(n=20_000, size=(128, 96), dtype=torch.float32, seed=7)
    weights = torch.randn(20_000, 6, generator=torch.Generator().manual_seed(8))
    results = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        maps = tex.clone().requires_grad_(True)
        gather = TextureGather(maps)
        u = uv.clone().requires_grad_(True)
        out = _joined(sh_texture)(maps, u, dirs, 3, NORMAL, gather=gather)
        (out * weights).sum().backward()
        results.append((out.detach(), _recorded(gather)[1], u.grad))
    for run in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(run, results[0], strict=True))
    stability.checked(27, "sh_texture: 1, 2, 3 threads, values and both gradients", 3)


def test_bad_input_is_a_named_error(stability):
    tex, uv, dirs = _case(n=6, dtype=torch.float32)
    _joined(sh_texture)(tex, uv, dirs, 3, NORMAL)
    other = TextureGather(tex.clone())
    bad = [
        (ShapeError, "tex", (tex[0], uv, dirs, 3), {}),
        (ShapeError, "uv", (tex, uv[:, :1], dirs, 3), {}),
        (ShapeError, "dirs", (tex, uv, dirs[:, :2], 3), {}),
        (ShapeError, "dirs", (tex, uv, dirs[:5], 3), {}),
        (DTypeError, "uv", (tex, uv.double(), dirs, 3), {}),
        (DTypeError, "dirs", (tex, uv, dirs.double(), 3), {}),
        (InvalidArgumentError, "degree", (tex, uv, dirs, 4), {}),
        (InvalidArgumentError, "extra", (tex, uv, dirs, 3, slice(40, 51)), {}),
        (InvalidArgumentError, "extra", (tex, uv, dirs, 3, slice(48, 60)), {}),
        (InvalidArgumentError, "extra", (tex, uv, dirs, 3, slice(48, 51, 2)), {}),
        (InvalidArgumentError, "tex", (tex[..., :40], uv, dirs, 3), {}),
        (InvalidArgumentError, "gather", (tex, uv, dirs, 3), {"gather": other}),
    ]
    for error, name, args, kwargs in bad:
        with pytest.raises(error, match=name):
            _joined(sh_texture)(*args, **kwargs)
    nan_dirs = dirs.clone()
    nan_dirs[2, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="dirs"):
        _joined(sh_texture)(tex, uv, nan_dirs, 3)
    nan_tex = tex.clone()
    nan_tex[:] = float("inf")
    with pytest.raises(NonFiniteError, match="tex"):
        _joined(sh_texture)(nan_tex, uv, dirs, 3)
    # No samples: empty values and gradients.
    u = torch.zeros(0, 2, requires_grad=True)
    out = _joined(sh_texture)(tex, u, torch.zeros(0, 3), 3, NORMAL)
    out.sum().backward()
    assert out.shape == (0, 6) and u.grad.shape == (0, 2)
    stability.checked(
        26, "sh_texture: wrong shapes, dtypes, ranges named; empty input", len(bad) + 2
    )


def _lookup_then_shade(maps, uv, dirs, degree, extra=None, *, gather=None):
    """What the mesh branch computed before the fused op: the whole rows, then the parts."""
    rows = texture(maps, uv) if gather is None else gather.sample(uv)
    return sh_shade(rows, dirs, degree), rows[:, extra or slice(0, 0)]


@pytest.mark.parametrize("shading", [False, True])
def test_avatar_mesh_branch_matches_the_lookup_path(shading, monkeypatch):
    """shade_mesh with the fused op against the rows-then-shade path, with and without
    pose-driven shading maps (read with the normal as one range): the same image, normals
    and recorded map gradient bit for bit, vertex gradients to rounding."""
    avatar = make_avatar(procedural_head(0), gaussians=False, sh_degree=2)
    g = torch.Generator().manual_seed(0)
    if shading:
        avatar.layout = MapLayout(2, False, shading=True)
        a = torch.randn(*avatar.maps.shape[:2], 9, generator=g) * 0.3
        avatar.maps = torch.cat([avatar.maps, a], -1)
    avatar.maps.requires_grad_(True)
    params = avatar.frame(3)
    pose = params.pose + torch.randn(params.pose.shape, generator=g) * 0.2
    params = params._replace(pose=pose)
    cam = camera(64)
    weights = torch.randn(64, 64, 3, generator=g)
    results = []
    for fn in (sh_texture, _lookup_then_shade):
        monkeypatch.setattr(urhead.model.avatar, "sh_texture", fn)
        gather = TextureGather(avatar.maps)
        verts, rotations = avatar.skin(params)
        displaced = verts.detach().requires_grad_(True)
        mesh = avatar.shade_mesh(displaced, displaced, rotations.detach(), cam, True, gather)
        ((mesh.image * weights).sum() + mesh.normals.sum()).backward()
        results.append(
            (mesh.image.detach(), mesh.normals.detach(), *_recorded(gather), displaced.grad)
        )
    (image, normals, s_uv, s_rows, g_verts), expected = results
    assert torch.equal(image, expected[0]) and torch.equal(normals, expected[1])
    assert torch.equal(s_uv, expected[2]) and torch.equal(s_rows, expected[3])
    assert s_rows[:, avatar.layout.normal].ne(0).any()
    assert torch.allclose(g_verts, expected[4], rtol=1e-4, atol=1e-5 * expected[4].abs().max())


# --- NUMERICS.md case 34 (urhead's own): float16 maps for frozen rendering ---------------


def test_case34_a_float16_texture_reads_as_its_float32_widening_exactly(stability):
    """Values and the UV gradient from a float16 texture are those of the float32 texture
    it widens to, bit for bit (the kernel widens each texel exactly, then runs the float32
    code), on both sides of the edge and with the extra channels."""
    tex, uv, dirs = _case(n=2000, size=(40, 31), dtype=torch.float32, seed=11)
    half = tex.half()
    weights = torch.randn(2000, 6, generator=torch.Generator().manual_seed(12))
    results = []
    for source in (half, half.float()):
        u = uv.clone().requires_grad_(True)
        out = _joined(sh_texture)(source, u, dirs, 3, NORMAL)
        (out * weights).sum().backward()
        results.append((out.detach(), u.grad))
    assert torch.equal(results[0][0], results[1][0])
    assert torch.equal(results[0][1], results[1][1])
    stability.checked(34, "float16 tex: values and UV gradient = its float32 widening's", 2000)


@pytest.mark.parametrize("degree", [0, 3])
def test_case34_float16_maps_stay_within_float16_rounding(degree, stability):
    """Against the float32 maps, the colour from their float16 copy errs by no more than
    the rounding of each coefficient (half a float16 spacing, ≤ 2⁻¹¹ relative, or 2⁻²⁵
    absolute below the smallest normal) weighted by its SH basis value — over maps that
    span float16's range: coefficients near ±65504, subnormal ones and typical ones."""
    g = torch.Generator().manual_seed(degree)
    n, size = 3000, (24, 20)
    tex = torch.randn(*size, CHANNELS, generator=g) * 0.5
    tex[0, :, :3] = 65000.0 * torch.sign(torch.randn(size[1], 3, generator=g))
    tex[1] = torch.randn(size[1], CHANNELS, generator=g) * 1e-6  # float16 subnormals
    tex[2] = torch.randn(size[1], CHANNELS, generator=g) * 300.0
    uv = torch.rand(n, 2, generator=g)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    half = urhead.ops.half_maps(tex)
    assert half is not None and half.dtype == torch.float16
    assert torch.equal(half, tex.to(torch.float16))  # rounded to nearest, as torch casts
    ours = _joined(sh_texture)(half, uv, dirs, degree, NORMAL).double()
    exact = _joined(_reference.sh_texture)(tex.double(), uv.double(), dirs.double(), degree, NORMAL)
    # Bound: Σ_k |b_k| · Σ_taps w · r(|c|), r(x) = max(x·2⁻¹¹, 2⁻²⁵), plus float32
    # arithmetic on the result (2⁻²³ relative of the terms' size, a few operations).
    rounding = torch.clamp(tex.double().abs() * 2.0**-11, min=2.0**-25)
    sizes = tex.double().abs()
    per_tap = _reference.texture(torch.cat([rounding, sizes], -1), uv.double())
    coefficients = 3 * (degree + 1) ** 2
    basis = _reference.sh_basis(dirs.double(), degree).abs()  # (n, K)
    colour_rounding = per_tap[:, :coefficients].reshape(n, -1, 3)
    colour_size = per_tap[:, CHANNELS : CHANNELS + coefficients].reshape(n, -1, 3)
    bound = torch.einsum("nk,nkc->nc", basis, colour_rounding)
    bound = bound + 8 * 2.0**-23 * (torch.einsum("nk,nkc->nc", basis, colour_size) + 0.5)
    normal_bound = per_tap[:, NORMAL] + 4 * 2.0**-23 * per_tap[:, CHANNELS:][:, NORMAL]
    worst = max(
        ((ours[:, :3] - exact[:, :3]).abs() / bound).max().item(),
        ((ours[:, 3:] - exact[:, 3:]).abs() / normal_bound).max().item(),
    )
    stability.record(34, f"float16 maps, degree {degree}: error / rounding bound", worst, 1.0)


def test_case34_maps_out_of_float16_range_get_no_float16_copy(stability):
    """Maps float16 cannot hold (a value beyond ±65504, or non-finite) get no copy, so the
    avatar keeps reading float32; the largest finite float16 itself is kept."""
    tex = torch.zeros(4, 4, CHANNELS)
    tex[1, 2, 7] = 65504.0
    assert urhead.ops.half_maps(tex)[1, 2, 7].item() == 65504.0
    cases = [7.0e4, -7.0e4, float("inf"), float("nan")]
    for value in cases:
        tex[3, 0, 50] = value
        assert urhead.ops.half_maps(tex) is None, value
    stability.checked(34, "maps beyond float16's range or non-finite: no float16 copy", 4)


def test_case34_a_float16_copy_of_leading_channels_checks_only_those():
    """``half_maps(tex, channels)`` copies the leading channels only, rounded as the whole
    copy's; a value float16 cannot hold past them does not stop the copy."""
    tex = torch.randn(5, 6, CHANNELS, generator=torch.Generator().manual_seed(3))
    tex[2, 3, CHANNELS - 1] = 1.0e6
    assert urhead.ops.half_maps(tex) is None
    lead = urhead.ops.half_maps(tex, 48)
    assert lead.shape == (5, 6, 48) and torch.equal(lead, tex[..., :48].half())
    tex[0, 0, 47] = float("nan")
    assert urhead.ops.half_maps(tex, 48) is None
    for bad in (0, CHANNELS + 1, 2.0, True):
        with pytest.raises(InvalidArgumentError, match="channels"):
            urhead.ops.half_maps(tex, bad)


def test_float16_texture_errors_are_named():
    tex, uv, dirs = _case(n=6, dtype=torch.float32)
    half = tex.half()
    with pytest.raises(InvalidArgumentError, match="float16 tex is read-only"):
        _joined(sh_texture)(half.clone().requires_grad_(True), uv, dirs, 3)
    with pytest.raises(InvalidArgumentError, match="float16 tex is read-only"):
        _joined(sh_texture)(half, uv, dirs, 3, gather=TextureGather(tex))
    with pytest.raises(DTypeError, match=r"uv must be torch\.float32"):
        _joined(sh_texture)(half, uv.double(), dirs, 3)
    with pytest.raises(DTypeError, match="float32"):
        urhead.ops.half_maps(tex.double())
    inf_tex = half.clone()
    inf_tex[:] = float("inf")
    with pytest.raises(NonFiniteError, match="tex"):
        _joined(sh_texture)(inf_tex, uv, dirs, 3)


def test_avatar_reads_a_kept_float16_copy_only_while_its_maps_are_frozen():
    """A frozen avatar's mesh branch reads one float16 copy of its maps' leading channels
    (the colour, or up to the last extra channel asked for: a prefix, so indices are the
    maps'), kept until the maps are edited in place or a wider prefix is asked for; a
    fit's maps (requiring grad, or with a gather) are read as they are. The frozen image
    is within float16 rounding of the float32 one."""
    avatar = make_avatar(procedural_head(0), gaussians=False, sh_degree=3)
    layout, maps = avatar.layout, avatar.maps
    assert not maps.requires_grad
    copy = avatar.pixel_maps_source()
    assert copy.dtype == torch.float16 and avatar.pixel_maps_source() is copy
    assert copy.shape == (*maps.shape[:2], layout.color.stop) < maps.shape
    assert torch.equal(copy, maps[..., : layout.color.stop].half())
    assert avatar.pixel_maps_source(TextureGather(maps)) is maps
    wider = avatar.pixel_maps_source(None, layout.normal)  # colour and normal: widened
    assert wider.shape[-1] == layout.normal.stop
    assert torch.equal(wider[..., : layout.color.stop], copy)
    assert avatar.pixel_maps_source() is wider  # a wider prefix serves the colour alone
    with torch.no_grad():  # an in-place edit (values float16 cannot hold): the copy is stale
        maps += torch.randn(maps.shape, generator=torch.Generator().manual_seed(0)) * 0.1
    fresh = avatar.pixel_maps_source()
    assert fresh is not wider and fresh.shape[-1] == layout.color.stop
    assert torch.allclose(fresh.float(), maps[..., : layout.color.stop], rtol=2.0**-11, atol=1e-7)
    params, cam = avatar.frame(3), camera(64)
    verts, rotations = avatar.skin(params)
    frozen = avatar.shade_mesh(verts, verts, rotations, cam, False).image
    maps.requires_grad_(True)
    assert avatar.pixel_maps_source() is maps
    trained = avatar.shade_mesh(verts, verts, rotations, cam, False).image.detach()
    assert 0 < (frozen - trained).abs().max() <= 2e-3
