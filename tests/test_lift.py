"""lift_gaussians_geometry: the Gaussian lift kernel against its plain-torch reference
(float64 values and every gradient), finite differences, NUMERICS case 19 (axis, near-
antipodal, tiny, huge, zero and NaN normals), threads (case 27), bad input (case 26), and
the avatar's lift before and after the kernel."""

from __future__ import annotations

import pytest
import torch

from test_model import camera, make_avatar
from urhead.errors import (
    DTypeError,
    IndexRangeError,
    InvalidArgumentError,
    NonFiniteError,
    ShapeError,
)
from urhead.head import procedural_head
from urhead.model import MapLayout
from urhead.model.lift_rows import lift_rows
from urhead.ops import _reference, lift_gaussians_geometry, sh_shade, texture

F64 = torch.float64
OUTPUTS = ("means", "normals", "quats", "frames", "view_dirs")
INPUTS = ("verts", "rotations", "normals", "lift")


def _rotations(v: int, g: torch.Generator, scale: float = 0.8) -> torch.Tensor:
    return _reference.axis_angle_to_matrix(torch.randn(v, 3, generator=g, dtype=F64) * scale)


def _case(n: int, v: int, seed: int = 0, dtype=F64) -> dict:
    g = torch.Generator().manual_seed(seed)
    bary = torch.rand(n, 3, generator=g, dtype=F64) + 0.05
    return {
        "verts": (torch.randn(v, 3, generator=g, dtype=F64) * 0.1).to(dtype),
        "rotations": _rotations(v, g).to(dtype),
        "face_verts": torch.randint(0, v, (n, 3), generator=g, dtype=torch.int32),
        "bary": (bary / bary.sum(1, keepdim=True)).to(dtype),
        "normals": torch.randn(n, 3, generator=g, dtype=F64).to(dtype),
        "lift": ((torch.rand(n, generator=g, dtype=F64) - 0.5) * 0.02).to(dtype),
        "centre": torch.tensor([0.05, -0.02, -1.0], dtype=dtype),
    }


AXES = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
NEAR_ANTIPODE = [[eps, 0, -1] for eps in (1.0, 1e-3, 1e-8, 1e-20, 1e-45, 0.0, -1e-20)]


def _special_case(seed: int = 0, magnitudes=(1.0, 1e-30, 1e30), dtype=F64) -> dict:
    """Random Gaussians plus, on identity-rotation vertices (so the posed normal is the
    rest normal), the axes and near-antipodal normals at each magnitude, a zero normal,
    degenerate barycentrics (one weight 1) and lifts 0 and 10."""
    case = _case(300, 40, seed)
    rot, faces, bary = case["rotations"], case["face_verts"], case["bary"]
    rot[:3] = torch.eye(3, dtype=F64)
    special = torch.tensor(AXES + NEAR_ANTIPODE, dtype=F64)
    normals = [case["normals"]] + [special * m for m in magnitudes]
    normals.append(torch.zeros(1, 3, dtype=F64))
    extra = sum(len(n) for n in normals[1:])
    lift = torch.cat([case["lift"], torch.full((extra,), 0.004, dtype=F64)])
    lift[::11] = 0.0
    lift[5::13] = 10.0
    g = torch.Generator().manual_seed(seed + 1)
    extra_bary = torch.rand(extra, 3, generator=g, dtype=F64) + 0.1
    extra_bary = extra_bary / extra_bary.sum(1, keepdim=True)
    extra_bary[::3] = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    extra_faces = torch.randint(0, 3, (extra, 3), generator=g, dtype=torch.int32)
    bary[::17] = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    out = dict(
        case,
        normals=torch.cat(normals),
        lift=lift,
        face_verts=torch.cat([faces, extra_faces]),
        bary=torch.cat([bary, extra_bary]),
    )
    return {k: v.to(dtype) if v.is_floating_point() else v for k, v in out.items()}


def _run(fn, case: dict, weights=None, needs=INPUTS):
    """Outputs, and with ``weights`` (one per differentiable output) the gradients of
    Σ w·output with respect to ``needs``."""
    leaves = {k: v.clone().requires_grad_(k in needs) for k, v in case.items()}
    out = fn(
        *(leaves[k] for k in ("verts", "rotations", "face_verts", "bary")),
        leaves["normals"],
        leaves["lift"],
        leaves["centre"],
    )
    out = dict(zip(OUTPUTS, out, strict=True))
    grads = {}
    if weights is not None:
        loss = sum((out[k] * w).sum() for k, w in weights.items())
        grads = dict(zip(needs, torch.autograd.grad(loss, [leaves[k] for k in needs]), strict=True))
    return {k: v.detach() for k, v in out.items()}, grads


def _weights(n: int, seed: int, dtype=F64) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g, dtype=F64).to(dtype),
        "normals": torch.randn(n, 3, generator=g, dtype=F64).to(dtype),
        "quats": torch.randn(n, 4, generator=g, dtype=F64).to(dtype),
    }


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a − b| over the scale of b's row (one Gaussian's or vertex's gradient): the
    rows span 1e-30 to 1e30 with tiny and huge normals."""
    scale = b.abs().flatten(1).amax(1) if b.dim() > 1 else b.abs()
    diff = (a - b).abs().flatten(1).amax(1) if b.dim() > 1 else (a - b).abs()
    return float((diff / scale.clamp_min(1e-300)).max())


def test_matches_reference_float64_values_and_gradients(stability):
    case = _special_case()
    n = len(case["lift"])
    weights = _weights(n, 1)
    ours, ours_g = _run(lift_gaussians_geometry, case, weights)
    ref, ref_g = _run(_reference.lift_gaussians_geometry, case, weights)
    for k in OUTPUTS:
        assert torch.isfinite(ours[k]).all(), k
        stability.close(19, f"lift {k} vs float64 reference", ours[k], ref[k], 1e-12, 1e-14)
    for k in INPUTS:
        assert torch.isfinite(ours_g[k]).all(), k
        err = _rel(ours_g[k], ref_g[k])
        stability.record(19, f"lift ∂/∂{k} vs float64 reference, per row", err, 1e-13)


def test_float32_agrees_with_float64():
    case64 = _special_case(seed=3, magnitudes=(1.0, 1e-30))
    case32 = {k: v.float() if v.is_floating_point() else v for k, v in case64.items()}
    n = len(case64["lift"])
    w64 = _weights(n, 2)
    w32 = {k: v.float() for k, v in w64.items()}
    out32, g32 = _run(lift_gaussians_geometry, case32, w32)
    out64, g64 = _run(lift_gaussians_geometry, case64, w64)
    for k in OUTPUTS:
        assert (out32[k].double() - out64[k]).abs().max() < 2e-6, k
    for k in INPUTS:
        # Tiny normals (1e-30) have gradients ~1e30: compare relative to each one's scale.
        a, b = g32[k].double(), g64[k]
        scale = b.abs().amax(-1, keepdim=True) if b.dim() > 1 else b.abs()
        assert ((a - b).abs() <= 2e-5 * scale + 1e-6).all(), k


def test_gradcheck_float64():
    case = _case(12, 5, seed=4)
    case["normals"][0] = torch.tensor([0.1, -0.2, -0.9], dtype=F64)  # the n_z < 0 branch
    case["bary"][1] = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    inputs = [case[k].clone().requires_grad_(True) for k in INPUTS]

    def fn(verts, rotations, normals, lift):
        out = lift_gaussians_geometry(
            verts, rotations, case["face_verts"], case["bary"], normals, lift, case["centre"]
        )
        return out.means, out.normals, out.quats

    assert torch.autograd.gradcheck(fn, inputs)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case19_lifted_quaternions_for_every_normal(dtype, stability):
    special = torch.tensor(AXES + NEAR_ANTIPODE, dtype=F64)
    g = torch.Generator().manual_seed(0)
    rand = torch.randn(100, 3, generator=g, dtype=F64)
    rand[::7, 2] = 0.0
    unit = torch.cat([special, rand])
    unit = unit / unit.norm(dim=-1, keepdim=True)
    n = len(unit)
    name = str(dtype)[6:]
    for magnitude in (1.0, 1e-30, 1e30):
        case = {
            "verts": torch.zeros(1, 3, dtype=dtype),
            "rotations": torch.eye(3, dtype=dtype)[None],
            "face_verts": torch.zeros(n, 3, dtype=torch.int32),
            "bary": torch.tensor([[0.5, 0.25, 0.25]], dtype=dtype).expand(n, 3),
            "normals": (torch.cat([special, rand]) * magnitude).to(dtype),
            "lift": torch.full((n,), 0.01, dtype=dtype),
            "centre": torch.tensor([0.0, 0.0, -1.0], dtype=dtype),
        }
        out, grads = _run(lift_gaussians_geometry, case, _weights(n, 5, dtype))
        q = out["quats"]
        assert all(torch.isfinite(t).all() for t in [*out.values(), *grads.values()])
        stability.close(19, f"lift |q| = 1 ({name})", q.norm(dim=-1), torch.ones(n), 1e-5, 1e-6)
        z_axis = _reference.quat_to_rotmat(q.double())[..., :, 2]
        stability.close(19, f"lift: local z = unit normal ({name})", z_axis, unit, 1e-5, 1e-5)
        if magnitude != 1e-30:  # below the 1e-12 floor n̂ is not unit (zero stays zero)
            assert torch.allclose(out["normals"].double(), unit, atol=1e-6)
    stability.checked(19, "lift: finite outputs and gradients, magnitudes 1, 1e-30, 1e30", 3 * n)


def test_case19_zero_and_non_finite_normals(stability):
    case = _case(20, 6, seed=7, dtype=torch.float32)
    bad = torch.tensor([[0.0, 0, 0], [float("nan"), 0, 1], [float("inf"), 0, 0]])
    case["normals"][:3] = bad
    out, _ = _run(lift_gaussians_geometry, case)
    assert torch.equal(out["quats"][:3], torch.tensor([[1.0, 0, 0, 0]] * 3))
    assert torch.equal(out["normals"][0], torch.zeros(3))
    assert torch.equal(
        out["means"][0],
        (case["verts"][case["face_verts"][0].long()] * case["bary"][0, :, None]).sum(0),
    )
    assert torch.isnan(out["means"][1]).all()
    # Seen only through their quaternions (a culled Gaussian's mean gradient is zero):
    # exactly zero gradient, and the other Gaussians' gradients as without them.
    weights = _weights(20, 3, torch.float32)
    weights["means"][:3] = 0.0
    weights["normals"][:3] = 0.0
    _, grads = _run(lift_gaussians_geometry, case, weights)
    assert all(torch.isfinite(g).all() for g in grads.values())
    assert (grads["normals"][:3] == 0).all() and (grads["lift"][:3] == 0).all()
    clean = dict(case, normals=case["normals"].clone())
    clean["normals"][:3] = torch.tensor([0.3, 0.2, 0.9])
    _, clean_grads = _run(lift_gaussians_geometry, clean, weights)
    assert torch.equal(grads["verts"], clean_grads["verts"])
    assert torch.equal(grads["normals"][3:], clean_grads["normals"][3:])
    stability.checked(19, "lift: zero, NaN, inf normal: identity, zero gradient", 3)
    # No upstream gradient at all: exact zeros, even through the NaN mean.
    leaves = {k: v.clone().requires_grad_(k in INPUTS) for k, v in case.items()}
    out = lift_gaussians_geometry(
        *(
            leaves[k]
            for k in ("verts", "rotations", "face_verts", "bary", "normals", "lift", "centre")
        )
    )
    torch.autograd.backward([out.means, out.quats], [torch.zeros(20, 3), torch.zeros(20, 4)])
    assert all((leaves[k].grad == 0).all() for k in INPUTS)


def test_case27_same_bits_for_any_thread_count(monkeypatch, stability):
    case = _case(20_000, 500, seed=9, dtype=torch.float32)
    weights = _weights(20_000, 6, torch.float32)
    results = []
    for threads in ("1", "2", "4"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        for _ in range(3):
            out, grads = _run(lift_gaussians_geometry, case, weights)
            results.append([*out.values(), *grads.values()])
    for run in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(run, results[0], strict=True))
    stability.checked(27, "lift: 1, 2, 4 threads × 3 runs, outputs and gradients", len(results))


def _call(case, **changes):
    args = dict(case, **changes)
    return lift_gaussians_geometry(
        args["verts"],
        args["rotations"],
        args["face_verts"],
        args["bary"],
        args["normals"],
        args["lift"],
        args["centre"],
    )


def test_case26_bad_input_is_a_named_error_before_any_work(stability):
    case = _case(8, 5, dtype=torch.float32)
    _call(case)
    bad = [
        (ShapeError, "verts", {"verts": torch.zeros(5, 4)}),
        (ShapeError, "rotations", {"rotations": torch.zeros(5, 9)}),
        (ShapeError, "rotations", {"rotations": torch.zeros(5, 2, 3)}),
        (ShapeError, "rotations", {"rotations": torch.zeros(4, 3, 3)}),
        (ShapeError, "face_verts", {"face_verts": torch.zeros(8, 4, dtype=torch.int32)}),
        (ShapeError, "bary", {"bary": torch.zeros(8, 2)}),
        (ShapeError, "bary", {"bary": torch.zeros(7, 3)}),
        (ShapeError, "normals", {"normals": torch.zeros(9, 3)}),
        (ShapeError, "lift", {"lift": torch.zeros(8, 1)}),
        (ShapeError, "lift", {"lift": torch.zeros(7)}),
        (ShapeError, "centre", {"centre": torch.zeros(4)}),
        (DTypeError, "normals", {"normals": torch.zeros(8, 3, dtype=F64)}),
        (DTypeError, "verts", {"verts": torch.zeros(5, 3, dtype=torch.int32)}),
        (DTypeError, "face_verts", {"face_verts": torch.zeros(8, 3)}),
        (DTypeError, "face_verts", {"face_verts": torch.full((8, 3), 2**40)}),
        (DTypeError, "lift", {"lift": [0.0] * 8}),
        (IndexRangeError, "face_verts", {"face_verts": torch.full((8, 3), 5, dtype=torch.int32)}),
        (IndexRangeError, "face_verts", {"face_verts": torch.full((8, 3), -1)}),
        (NonFiniteError, "verts", {"verts": torch.full((5, 3), float("nan"))}),
        (NonFiniteError, "rotations", {"rotations": torch.full((5, 3, 3), float("inf"))}),
        (NonFiniteError, "bary", {"bary": torch.full((8, 3), float("nan"))}),
        (InvalidArgumentError, "bary", {"bary": case["bary"].clone().requires_grad_(True)}),
    ]
    for error, name, change in bad:
        with pytest.raises(error, match=name):
            _call(case, **change)
    # Non-contiguous inputs are made contiguous; int64 face ids are converted.
    wide = torch.zeros(5, 6)
    wide[:, ::2] = case["verts"]
    same = _call(case, verts=wide[:, ::2], face_verts=case["face_verts"].long())
    assert torch.equal(same.means, _call(case).means)
    # No Gaussians: empty outputs, a zero vertex gradient.
    verts = case["verts"].clone().requires_grad_(True)
    empty = _call(
        case,
        verts=verts,
        face_verts=torch.zeros(0, 3, dtype=torch.int32),
        bary=torch.zeros(0, 3),
        normals=torch.zeros(0, 3),
        lift=torch.zeros(0),
    )
    assert empty.means.shape == (0, 3) and empty.frames.shape == (0, 3, 3)
    empty.means.sum().backward()
    assert torch.equal(verts.grad, torch.zeros(5, 3))
    stability.checked(26, "lift: wrong shape, dtype, range, non-finite geometry", len(bad))


# The avatar ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def head():
    return procedural_head(0)


def _old_colour(layout, rows, dirs, frames):
    """SH colour along the rest-frame directions, times the shading gain with shading maps."""
    rgb = _reference.sh_shade(rows, dirs, layout.sh_degree)
    if not layout.shading:
        return rgb
    features = (frames - torch.eye(3)).reshape(-1, 9)
    return rgb * (1 + (rows[:, layout.shading_maps] * features).sum(-1))[:, None]


def _old_lift(avatar, verts, rotations, cam):
    """The avatar's lift before the kernel: plain torch around the map lookup and SH."""
    layout = avatar.layout
    rows = texture(avatar.maps, avatar.gaussian_uv)
    samples = layout.split(rows)
    lift = samples.displacement
    if samples.offset is not None:
        lift = lift + samples.offset
    face_verts = avatar.tables().faces_long[avatar.gaussian_face]
    means, _, quats, frames, dirs = _reference.lift_gaussians_geometry(
        verts, rotations, face_verts, avatar.gaussian_bary, samples.normal, lift, cam.center
    )
    return {
        "means": means,
        "quats": quats,
        "scales": samples.scale.exp(),
        "opacities": torch.sigmoid(samples.opacity),
        "colors": _old_colour(layout, rows, dirs, frames),
        "frames": frames,
    }


@pytest.mark.parametrize("offsets", [False, True])
@pytest.mark.parametrize("shading", [False, True])
def test_avatar_lift_agrees_with_the_torch_path(head, offsets, shading):
    avatar = make_avatar(head, sh_degree=2, count=300)
    layout = MapLayout(2, True, offsets=offsets, shading=shading)
    g = torch.Generator().manual_seed(0)
    base = avatar.maps
    extra = torch.randn(*base.shape[:2], layout.channels - base.shape[2], generator=g) * 0.01
    maps = torch.cat([base, extra], -1)
    maps[..., layout.normal] += torch.randn(*base.shape[:2], 3, generator=g) * 0.3
    maps[..., layout.displacement] += torch.randn(*base.shape[:2], generator=g) * 0.003
    avatar.layout, avatar.maps = layout, maps.requires_grad_(True)
    params = avatar.frame(3)
    pose = torch.randn(params.pose.shape, generator=g) * 0.2
    with torch.no_grad():
        verts, rotations = avatar.skin(params._replace(pose=pose))
    cam = camera()
    keys = ("means", "quats", "scales", "opacities", "colors")
    weights = {
        k: torch.randn(avatar.num_gaussians, *s, generator=g)
        for k, s in zip(keys, ((3,), (4,), (3,), (), (3,)), strict=True)
    }
    results = []
    for lift_fn in (
        lambda v, r: avatar.lift_gaussians(v, r, cam)._asdict(),
        lambda v, r: _old_lift(avatar, v, r, cam),
    ):
        v, r = verts.clone().requires_grad_(True), rotations.clone().requires_grad_(True)
        avatar.maps.grad = None
        out = lift_fn(v, r)
        sum((out[k] * weights[k]).sum() for k in keys).backward()
        results.append((out, v.grad, r.grad, avatar.maps.grad.to_dense()))
    (new, *new_grads), (old, *old_grads) = results
    for k in (*keys, "frames"):
        assert torch.allclose(new[k], old[k], rtol=1e-5, atol=1e-6), k
    for name, a, b in zip(("verts", "rotations", "maps"), new_grads, old_grads, strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5 * b.abs().max()), name
    assert torch.equal(new["frames"], avatar.lift_gaussians(verts, rotations, cam).frames)


def test_avatar_face_vertex_ids_follow_the_gaussians(head):
    avatar = make_avatar(head, count=30)
    ids = avatar.gaussian_face_verts()
    assert ids.dtype == torch.int32 and avatar.gaussian_face_verts() is ids
    assert torch.equal(ids.long(), avatar.tables().faces_long[avatar.gaussian_face])
    avatar.gaussian_face = avatar.gaussian_face.flip(0)
    assert torch.equal(avatar.gaussian_face_verts().long()[0], ids.long()[-1])
    with torch.no_grad():
        avatar.gaussian_face[0] = 0
    assert torch.equal(avatar.gaussian_face_verts()[0], avatar.tables().faces[0])


def _composed_lift(rows, layout, verts, rotations, face_verts, bary, centre):
    """The lift from map rows as separate ops (split, geometry kernel, exp, sigmoid, SH
    colour, shading gain): what :func:`lift_rows` fuses into one node."""
    samples = layout.split(rows)
    lift = samples.displacement
    if samples.offset is not None:
        lift = lift + samples.offset
    geometry = lift_gaussians_geometry(
        verts, rotations, face_verts, bary, samples.normal, lift, centre
    )
    rgb = sh_shade(rows, geometry.view_dirs, layout.sh_degree)
    if layout.shading:
        features = (geometry.frames - torch.eye(3)).reshape(-1, 9)
        rgb = rgb * (1 + (rows[:, layout.shading_maps] * features).sum(-1))[:, None]
    return {
        "means": geometry.means,
        "quats": geometry.quats,
        "scales": samples.scale.contiguous().exp(),
        "opacities": torch.sigmoid(samples.opacity.contiguous()),
        "colors": rgb,
        "frames": geometry.frames,
        "offset": samples.offset,
    }


@pytest.mark.parametrize("offsets", [False, True])
@pytest.mark.parametrize("shading", [False, True])
def test_lift_rows_is_the_composed_ops_bit_for_bit(offsets, shading):
    """Values and gradients (rows, vertices, rotations) equal to the separate ops', some
    outputs without a gradient; rows without gradient (a frozen avatar) give the same
    values."""
    g = torch.Generator().manual_seed(7)
    layout = MapLayout(3, True, offsets=offsets, shading=shading)
    n, v = 500, 40
    rows = torch.randn(n, layout.channels, generator=g)
    rows[:, layout.color] *= 0.3
    rows[:, layout.displacement] *= 0.01
    verts = torch.randn(v, 3, generator=g)
    rotations = torch.linalg.matrix_exp(_skew(torch.randn(v, 3, generator=g) * 0.3))
    face_verts = torch.randint(0, v, (n, 3), generator=g, dtype=torch.int32)
    bary = torch.rand(n, 3, generator=g)
    bary /= bary.sum(1, keepdim=True)
    centre = torch.tensor([0.1, -0.2, 3.0])
    keys = ["means", "quats", "scales", "opacities", "colors"] + (["offset"] if offsets else [])
    weights = {
        k: torch.randn(
            n,
            *((4,) if k == "quats" else (3,) if k in ("means", "scales", "colors") else ()),
            generator=g,
        )
        for k in keys
    }
    results = []
    for fn in (
        lambda *a: lift_rows(a[0], layout, *a[1:], layout.sh_degree)._asdict(),
        lambda *a: _composed_lift(a[0], layout, *a[1:]),
    ):
        leaves = [t.clone().requires_grad_(True) for t in (rows, verts, rotations)]
        out = fn(*leaves, face_verts, bary, centre)
        # One output takes no gradient (the scales, or the colours): handled either way.
        skipped = "scales" if offsets else "colors"
        sum((out[k] * weights[k]).sum() for k in keys if k != skipped).backward()
        results.append((out, [t.grad for t in leaves]))
    (new, new_grads), (old, old_grads) = results
    for k in (*keys, "frames"):
        assert torch.equal(new[k], old[k]), k
    for name, a, b in zip(("rows", "verts", "rotations"), new_grads, old_grads, strict=True):
        assert torch.equal(a, b), name
    with torch.no_grad():
        frozen = lift_rows(rows, layout, verts, rotations, face_verts, bary, centre, 3)
    assert all(torch.equal(getattr(frozen, k), new[k]) for k in keys)
    with pytest.raises(ValueError, match="rows must be"):
        lift_rows(rows[:, 1:], layout, verts, rotations, face_verts, bary, centre, 3)


def _skew(w):
    zero = torch.zeros_like(w[:, 0])
    return torch.stack(
        [zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], 1
    ).reshape(-1, 3, 3)
