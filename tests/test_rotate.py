"""rotate_normalize: the kernel against its plain-torch reference (float64 values and both
gradients, both orientations), finite differences, zero, tiny, huge and non-finite
vectors, non-orthogonal matrices, threads, bad input, and the avatar's mesh branch before
and after the kernel."""

from __future__ import annotations

import pytest
import torch

import urhead.model.avatar
from test_model import camera, make_avatar
from urhead.errors import DTypeError, IndexRangeError, InvalidArgumentError, ShapeError
from urhead.head import procedural_head
from urhead.ops import TextureGather, _reference, rotate_normalize

F64 = torch.float64
NAN, INF = float("nan"), float("inf")


def _case(n: int, seed: int = 0, dtype=F64, orthogonal: bool = False):
    """Rotations, or identity plus a perturbation (not orthogonal), and random vectors."""
    g = torch.Generator().manual_seed(seed)
    if orthogonal:
        rotations = _reference.axis_angle_to_matrix(torch.randn(n, 3, generator=g, dtype=F64))
    else:
        rotations = torch.eye(3, dtype=F64) + (torch.rand(n, 3, 3, generator=g, dtype=F64) - 0.5)
    vectors = torch.randn(n, 3, generator=g, dtype=F64)
    return rotations.to(dtype), vectors.to(dtype)


def _special_case(magnitudes=(1.0, 1e-12, 1e-13, 1e-30, 1e30), dtype=F64):
    """Random rows, then the same rows scaled to each magnitude (around the 1e-12 floor,
    below it, beyond float32's squared range), and a zero vector."""
    rotations, vectors = _case(60, seed=1)
    rows = torch.cat([vectors * m for m in magnitudes] + [torch.zeros(1, 3, dtype=F64)])
    rots = torch.cat([rotations] * len(magnitudes) + [rotations[:1]])
    return rots.to(dtype), rows.to(dtype)


def _run(fn, rotations, vectors, transpose, weights, needs=(True, True)):
    """The output and the gradients of Σ w·output to the inputs flagged in ``needs``
    (None for the others)."""
    r = rotations.clone().requires_grad_(needs[0])
    v = vectors.clone().requires_grad_(needs[1])
    out = fn(r, v, transpose)
    (out * weights).sum().backward()
    return out.detach(), r.grad, v.grad


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a − b| over the scale of b's row: rows span 1e-30 to 1e30."""
    scale = b.abs().flatten(1).amax(1).clamp_min(1e-300)
    return float(((a - b).abs().flatten(1).amax(1) / scale).max())


@pytest.mark.parametrize("transpose", [False, True])
def test_matches_reference_float64_values_and_gradients(transpose, stability):
    rotations, vectors = _special_case()
    weights = torch.randn(vectors.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    ours = _run(rotate_normalize, rotations, vectors, transpose, weights)
    ref = _run(_reference.rotate_normalize, rotations, vectors, transpose, weights)
    assert torch.allclose(ours[0], ref[0], rtol=1e-14, atol=1e-15)
    assert ours[0][-1].eq(0).all(), "a zero vector stays zero"
    for a, b in zip(ours[1:], ref[1:], strict=True):
        assert torch.isfinite(a).all()
        assert _rel(a, b) < 1e-13
    stability.checked(19, "rotate_normalize vs float64 reference, magnitudes 1 … 1e30, zero", 60)


def test_float32_agrees_with_float64_reference():
    rotations, vectors = _special_case()
    weights = torch.randn(vectors.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    for transpose in (False, True):
        got = _run(rotate_normalize, rotations.float(), vectors.float(), transpose, weights.float())
        ref = _run(_reference.rotate_normalize, rotations, vectors, transpose, weights)
        # 1e30 rows are normalised here; torch's own float32 |m| overflows to inf there.
        assert (got[0].double() - ref[0]).abs().max() < 2e-6
        for a, b in zip(got[1:], ref[1:], strict=True):
            assert _rel(a.double(), b) < 2e-5


@pytest.mark.parametrize("transpose", [False, True])
def test_gradcheck_float64(transpose):
    rotations, vectors = _case(10, seed=4)
    inputs = (rotations.requires_grad_(True), vectors.requires_grad_(True))
    assert torch.autograd.gradcheck(lambda r, v: rotate_normalize(r, v, transpose), inputs)


def test_zero_and_non_finite_vectors_behave_as_the_torch_expression(stability):
    rotations, vectors = _case(8, seed=5)
    rotations[3:] = torch.eye(3, dtype=F64)
    vectors[:5] = torch.tensor(
        [[0.0, 0, 0], [NAN, 0, 1], [INF, 0, 0], [1e300, -1e300, 0], [0.6, 0, 0.8]], dtype=F64
    )
    rotations[5, 0, 0] = INF  # an infinite product (±inf, finite, finite): (NaN, 0, 0)
    rotations[6, 1, 2] = NAN
    weights = torch.randn(8, 3, generator=torch.Generator().manual_seed(6), dtype=F64)
    weights[1] = 0.0  # a zero upstream gradient does not hide the NaN (torch's 0/NaN)
    same = [0, 1, 2, 4, 5, 6, 7]
    for transpose in (False, True):
        ours = _run(rotate_normalize, rotations, vectors, transpose, weights)
        ref = _run(_reference.rotate_normalize, rotations, vectors, transpose, weights)
        for a, b in zip(ours, ref, strict=True):
            a, b = a[same], b[same]
            finite = torch.isfinite(b)
            assert torch.equal(torch.isnan(a), torch.isnan(b)) and finite.any()
            assert torch.allclose(a[finite], b[finite], rtol=1e-14, atol=0)
        out, r_grad, v_grad = ours
        r0, g0 = rotations[0], weights[0]
        assert out[0].eq(0).all(), "a zero vector stays zero"
        expected = (r0 @ g0 if transpose else g0 @ r0) / 1e-12  # the gradient of m / 1e-12
        assert torch.allclose(v_grad[0], expected, rtol=1e-15, atol=0)
        assert torch.isnan(out[[1, 2, 6]]).all() and torch.isnan(v_grad[[1, 2, 5, 6]]).all()
        assert out[5, 0].isnan() and out[5, 1:].eq(0).all()
        # Huge but finite: normalised, where the reference's |m|² overflows to a zero vector.
        half = 0.5**0.5
        assert torch.allclose(out[3], torch.tensor([half, -half, 0], dtype=F64))
        assert ref[0][3].eq(0).all()
        assert torch.isfinite(r_grad[[0, 3, 4, 7]]).all()
        assert torch.isfinite(v_grad[[0, 3, 4, 7]]).all()
    stability.checked(19, "rotate_normalize: zero, NaN, inf, 1e300 vectors as documented", 8)


def test_only_the_requested_gradients():
    rotations, vectors = _case(50, seed=7, dtype=torch.float32, orthogonal=True)
    weights = torch.randn(50, 3, generator=torch.Generator().manual_seed(8))
    _, r_both, v_both = _run(rotate_normalize, rotations, vectors, False, weights)
    _, r_only, v_none = _run(rotate_normalize, rotations, vectors, False, weights, (True, False))
    _, r_none, v_only = _run(rotate_normalize, rotations, vectors, False, weights, (False, True))
    assert v_none is None and r_none is None
    assert torch.equal(r_only, r_both) and torch.equal(v_only, v_both)
    # No gradient at all: no graph.
    assert not rotate_normalize(rotations, vectors, transpose=True).requires_grad


def test_same_bits_for_any_thread_count(monkeypatch, stability):
    rotations, vectors = _case(20_000, seed=9, dtype=torch.float32)
    weights = torch.randn(20_000, 3, generator=torch.Generator().manual_seed(10))
    for transpose in (False, True):
        results = []
        for threads in ("1", "2", "3"):
            monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
            results.append(_run(rotate_normalize, rotations, vectors, transpose, weights))
        for run in results[1:]:
            assert all(torch.equal(a, b) for a, b in zip(run, results[0], strict=True))
    stability.checked(27, "rotate_normalize: 1, 2, 3 threads, outputs and gradients", 6)


def test_bad_input_is_a_named_error(stability):
    rotations, vectors = _case(6, dtype=torch.float32)
    rotate_normalize(rotations, vectors)
    bad = [
        (ShapeError, "rotations", (rotations.reshape(6, 9), vectors)),
        (ShapeError, "rotations", (rotations[:, :2], vectors)),
        (ShapeError, "rotations", (rotations[:5], vectors)),
        (ShapeError, "vectors", (rotations, vectors[:, :2])),
        (ShapeError, "vectors", (rotations, vectors[None])),
        (DTypeError, "rotations", (rotations.int(), vectors)),
        (DTypeError, "rotations", (rotations.numpy(), vectors)),
        (DTypeError, "vectors", (rotations, vectors.double())),
        (DTypeError, "vectors", (rotations, vectors.tolist())),
    ]
    for error, name, args in bad:
        with pytest.raises(error, match=name):
            rotate_normalize(*args)
    # Non-contiguous inputs are made contiguous (their gradient flows back through the view).
    wide = torch.zeros(6, 5)
    wide[:, 1:4] = vectors
    wide.requires_grad_(True)
    out = rotate_normalize(rotations.transpose(1, 2), wide[:, 1:4], transpose=True)
    assert torch.equal(out, rotate_normalize(rotations, vectors))
    out.sum().backward()
    assert wide.grad[:, [0, 4]].eq(0).all() and wide.grad[:, 1:4].ne(0).any()
    # No rows: an empty output and empty gradients.
    empty_r = torch.zeros(0, 3, 3, requires_grad=True)
    rotate_normalize(empty_r, torch.zeros(0, 3)).sum().backward()
    assert empty_r.grad.shape == (0, 3, 3)
    stability.checked(26, "rotate_normalize: wrong shapes and dtypes named, empty input", len(bad))


@pytest.mark.parametrize("transpose", [False, True])
def test_rows_pick_from_a_table_as_indexing_does(transpose):
    """``rows`` reads ``vectors[rows]`` in place: against the float64 reference that indexes
    first (values, rotation gradient), bit for bit against the kernel on the indexed copy in
    float32, and the table gets no gradient."""
    rotations, _ = _case(500, seed=4)
    table = torch.randn(2000, 3, generator=torch.Generator().manual_seed(5), dtype=F64)
    rows = torch.randint(0, 2000, (500,), generator=torch.Generator().manual_seed(6)).sort()[0]
    rows[1] = rows[0]  # repeats allowed
    weights = torch.randn(500, 3, generator=torch.Generator().manual_seed(7), dtype=F64)
    results = []
    for fn in (rotate_normalize, _reference.rotate_normalize):
        r = rotations.clone().requires_grad_(True)
        out = fn(r, table, transpose, rows)
        (out * weights).sum().backward()
        results.append((out.detach(), r.grad))
    (ours, g_ours), (ref, g_ref) = results
    assert _rel(ours, ref) < 1e-14 and _rel(g_ours, g_ref) < 1e-13
    r32, t32 = rotations.float(), table.float()
    picked = rotate_normalize(r32, t32, transpose, rows)
    assert torch.equal(picked, rotate_normalize(r32, t32[rows].contiguous(), transpose))


def test_bad_rows_are_named_errors():
    rotations, _ = _case(6, dtype=torch.float32)
    table = torch.randn(10, 3)
    rows = torch.tensor([0, 3, 3, 9, 2, 5])
    rotate_normalize(rotations, table, rows=rows)
    bad = [
        (IndexRangeError, "rows", (table, rows.clone().index_fill_(0, torch.tensor([3]), 10))),
        (IndexRangeError, "rows", (table, rows.clone().index_fill_(0, torch.tensor([2]), -1))),
        (ShapeError, "rotations", (table, rows[:5])),
        (ShapeError, "rows", (table, rows[None])),
        (DTypeError, "rows", (table, rows.int())),
        (ShapeError, "vectors", (table[:, :2], rows)),
        (InvalidArgumentError, "no gradient", (table.clone().requires_grad_(True), rows)),
    ]
    for error, name, (vectors, picked) in bad:
        with pytest.raises(error, match=name):
            rotate_normalize(rotations, vectors, rows=picked)


# The avatar ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def head():
    return procedural_head(0)


def test_avatar_mesh_branch_agrees_with_the_bmm_path(head, monkeypatch):
    """displace and shade_mesh (colour view directions and normals) with the kernel and
    with the plain-torch ``bmm`` they used before: same images, normals and gradients."""
    avatar = make_avatar(head, gaussians=False, sh_degree=2)
    g = torch.Generator().manual_seed(0)
    layout = avatar.layout
    with torch.no_grad():
        avatar.maps[..., layout.normal] += torch.randn(*avatar.maps.shape[:2], 3, generator=g) * 0.3
    params = avatar.frame(3)
    pose = torch.randn(params.pose.shape, generator=g) * 0.2
    results = []
    for fn in (rotate_normalize, _reference.rotate_normalize):
        monkeypatch.setattr(urhead.model.avatar, "rotate_normalize", fn)
        leaf = pose.clone().requires_grad_(True)
        gather = TextureGather(avatar.maps.requires_grad_(True))
        out = avatar.render(params._replace(pose=leaf), camera(), normals=True, gather=gather)
        (out.image.square().sum() + out.mesh.normals[:, 2].sum()).backward()
        results.append(
            (out.image.detach(), out.mesh.normals.detach(), leaf.grad, gather.gradient().to_dense())
        )
    for name, a, b in zip(("image", "normals", "pose", "maps"), *results, strict=True):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6 * b.abs().max().item()), name
