"""urhead.optim.SparseAdam against the plain-torch reference, NUMERICS.md cases 25 and 33
(bfloat16 moments), and the sparse contract (untouched texels bit-identical, sparse and
dense gradients agree)."""

import math

import pytest
import torch

from urhead.errors import DTypeError, InvalidArgumentError, ShapeError
from urhead.ops import TextureGather
from urhead.ops import _reference as ref
from urhead.optim import RowJournal, SparseAdam, moment_array

H, W, C = 16, 12, 5
LR = torch.tensor([5e-4, 1e-3, 5e-3, 5e-2, 1e-5])
MOMENTS = ["float32", "bfloat16"]


def sparse_grad(rows, values):
    index = torch.stack([rows // W, rows % W])
    return torch.sparse_coo_tensor(index, values, (H, W, C), check_invariants=True)


def test_matches_reference_over_steps_with_changing_texel_sets():
    g = torch.Generator().manual_seed(0)
    param = torch.randn(H, W, C, generator=g)
    # The reference computes in float64 but stores into float32 tables, as the kernel does.
    expect = param.reshape(-1, C).clone()
    m = torch.zeros_like(expect)
    v = torch.zeros_like(expect)
    steps = torch.zeros(H * W, dtype=torch.int64)
    opt = SparseAdam([param], lr=LR)
    for it in range(12):
        rows = torch.randperm(H * W, generator=g)[: 20 + it * 5].sort().values
        values = torch.randn(rows.numel(), C, generator=g) * 10 ** (it % 4 - 2)
        param.grad = sparse_grad(rows, values)
        opt.step()
        ref.sparse_adam_step(expect, m, v, steps, rows, values, LR, 0.9, 0.999, 1e-15)
    assert (param.reshape(-1, C) - expect).abs().max() < 1e-6
    assert torch.equal(opt.state[param]["steps"].long(), steps)


def test_untouched_texels_stay_bit_identical_and_sparse_equals_dense():
    g = torch.Generator().manual_seed(1)
    a = torch.randn(H, W, C, generator=g)
    b = a.clone()
    before = a.clone()
    rows = torch.tensor([3, 40, 41, 100])
    values = torch.randn(4, C, generator=g)
    a.grad = sparse_grad(rows, values)
    dense = torch.zeros(H * W, C)
    dense[rows] = values
    b.grad = dense.reshape(H, W, C)
    SparseAdam([a], lr=LR).step()
    SparseAdam([b], lr=LR).step()
    assert torch.equal(a, b)
    untouched = torch.ones(H * W, dtype=torch.bool)
    untouched[rows] = False
    assert torch.equal(a.reshape(-1, C)[untouched], before.reshape(-1, C)[untouched])
    assert not torch.equal(a.reshape(-1, C)[rows], before.reshape(-1, C)[rows])


def test_uncoalesced_sparse_gradients_are_summed():
    # Two texture lookups of one map accumulate as an uncoalesced sparse gradient.
    a = torch.zeros(H, W, C)
    b = torch.zeros(H, W, C)
    rows = torch.tensor([7, 7, 9])
    values = torch.tensor([[1.0] * C, [2.0] * C, [-1.0] * C])
    a.grad = sparse_grad(rows, values)
    b.grad = sparse_grad(torch.tensor([7, 9]), torch.tensor([[3.0] * C, [-1.0] * C]))
    SparseAdam([a], lr=LR).step()
    SparseAdam([b], lr=LR).step()
    assert torch.equal(a, b)


@pytest.mark.parametrize("bad", [float("inf"), -float("inf"), float("nan")])
def test_case25_extreme_gradients(bad, stability):
    param = torch.zeros(H, W, C)
    before = param.clone()
    opt = SparseAdam([param], lr=LR)
    rows = torch.tensor([0, 1, 2, 3, 4])
    values = torch.zeros(5, C)
    values[1] = 1e-30
    values[2] = 1e20
    values[3, 2] = bad  # one bad channel rejects the whole texel
    values[4] = -1e20
    for _ in range(3):
        param.grad = sparse_grad(rows, values)
        opt.step()
    flat = param.reshape(-1, C)
    assert torch.isfinite(param).all()
    bound = LR * max(1.0, 0.1 / 0.001**0.5) * 3 + 1e-9
    step_ratio = (flat.abs() / bound).max()  # the bound is per channel (lr per channel)
    stability.record(25, "max |3 steps| / (3·lr·max(1, (1 − β1)/√(1 − β2)))", step_ratio, 1)
    assert (flat.abs() <= bound).all()
    moved = (flat - before.reshape(-1, C)).abs()
    stability.record(25, "zero-gradient texel: max |change|", moved[0].max(), 0)
    assert torch.equal(flat[0], before.reshape(-1, C)[0])  # zero gradient: no move
    stability.record(
        25, "texel with a non-finite gradient (rejected): max |change|", moved[3].max(), 0
    )
    assert torch.equal(flat[3], before.reshape(-1, C)[3])  # rejected
    stability.record(25, "untouched texels: max |change|", moved[5:].max(), 0)
    assert torch.equal(flat[5:], before.reshape(-1, C)[5:])  # untouched
    assert (flat[2] < 0).all() and (flat[4] > 0).all()
    state = opt.state[param]
    assert state["rejected_rows"] == 3
    assert state["steps"][3] == 0 and state["steps"][2] == 3
    assert torch.isfinite(state["exp_avg_sq"]).all() and torch.isfinite(state["exp_avg"]).all()
    stability.checked(
        25, "1e20 and 1e-30 gradients: finite moments, steps in the right direction", 3
    )


def test_bad_arguments_are_named():
    with pytest.raises(ShapeError, match="lr must"):
        p = torch.zeros(4, 3)
        p.grad = torch.ones(4, 3)
        SparseAdam([p], lr=[0.1, 0.2]).step()
    with pytest.raises(InvalidArgumentError, match="sparse gradient"):
        p = torch.zeros(4, 3)
        p.grad = torch.ones(4, 3).to_sparse()
        SparseAdam([p], lr=0.1).step()
    with pytest.raises(InvalidArgumentError, match="beta1"):
        p = torch.zeros(4, 3)
        p.grad = torch.ones(4, 3)
        SparseAdam([p], lr=0.1, betas=(1.0, 0.999)).step()


@pytest.mark.parametrize("moments", MOMENTS)
def test_deterministic_across_thread_counts(monkeypatch, stability, moments):
    results = []
    for n in ("1", "2", "3"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", n)
        g = torch.Generator().manual_seed(2)
        p = torch.randn(64, 64, C, generator=g)
        opt = SparseAdam([p], lr=LR, moments=moments)
        for _ in range(3):
            rows = torch.randperm(64 * 64, generator=g)[:1500].sort().values
            values = torch.randn(1500, C, generator=g)
            p.grad = torch.sparse_coo_tensor(
                torch.stack([rows // 64, rows % 64]), values, (64, 64, C), check_invariants=True
            )
            opt.step()
        state = opt.state[p]
        results.append(torch.cat([p, state["exp_avg"].float(), state["exp_avg_sq"].float()]))
    differing = sum(int((r != results[0]).sum()) for r in results)
    stability.record(
        27,
        f"sparse Adam ({moments} moments): elements differing across 1, 2, 3 threads",
        differing,
        0,
    )
    assert all(torch.equal(r, results[0]) for r in results)


def test_state_dict_round_trip_keeps_int32_steps_and_continues_identically():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(8, 8, 3, generator=g)
    b = a.clone()
    opt_a, opt_b = SparseAdam([a], lr=1e-2), SparseAdam([b], lr=1e-2)
    grads = [
        torch.randn(8, 8, 3, generator=g) * (torch.rand(8, 8, 1, generator=g) > 0.5)
        for _ in range(4)
    ]
    for grad in grads[:2]:
        a.grad, b.grad = grad.clone(), grad.clone()
        opt_a.step()
        opt_b.step()
    restored = SparseAdam([b], lr=1e-2)
    restored.load_state_dict(opt_b.state_dict())
    assert restored.state[b]["steps"].dtype == torch.int32
    for grad in grads[2:]:
        a.grad, b.grad = grad.clone(), grad.clone()
        opt_a.step()
        restored.step()
    assert torch.equal(a, b)


@pytest.mark.parametrize("moments", MOMENTS)
def test_a_reported_step_gives_channel_peaks_and_a_journal_undoes_its_steps_exactly(moments):
    g = torch.Generator().manual_seed(3)
    param = torch.randn(H, W, C, generator=g)
    opt = SparseAdam([param], lr=LR, moments=moments)
    param.grad = sparse_grad(torch.tensor([0, 5]), torch.randn(2, C, generator=g))
    opt.step()  # moments exist and are non-zero before the journal starts
    state = opt.state[param]
    before = [t.clone() for t in (param, state["exp_avg"], state["exp_avg_sq"], state["steps"])]
    journal = RowJournal(H * W, C, moments)
    for it in range(3):
        rows = torch.tensor([5, 7 + it, 30])
        values = torch.randn(3, C, generator=g)
        values[2, 1] = float("nan") if it == 1 else values[2, 1]
        param.grad = sparse_grad(rows, values)
        report = opt.step_reported(journal)
        expected = values.abs().amax(0)
        expected[1] = math.inf if it == 1 else expected[1]
        assert torch.equal(report.peaks, expected)
        assert (report.rejected_rows, report.non_finite_rows) == (int(it == 1), 0)
    assert len(journal) == 5  # rows 5, 7, 8, 9, 30, each saved once
    journal.restore(
        param.reshape(-1, C).numpy(),
        moment_array(state["exp_avg"].reshape(-1, C)),
        moment_array(state["exp_avg_sq"].reshape(-1, C)),
        state["steps"].numpy(),
    )
    after = (param, state["exp_avg"], state["exp_avg_sq"], state["steps"])
    assert all(torch.equal(a, b) for a, b in zip(after, before, strict=True))


def lookups(g, count, channels):
    """Bilinear lookups as a fit records them: UVs (some shared, one NaN, some outside the
    atlas) and output gradients (some rows zero)."""
    uv = torch.rand(count, 2, generator=g) * 1.2 - 0.1
    uv[count // 2 :: 7] = uv[: len(uv[count // 2 :: 7])]  # several lookups of one point
    uv[3] = float("nan")
    v_out = torch.randn(count, channels, generator=g)
    v_out[::5] = 0
    return uv, v_out


SPLITS = [[3000], [0, 3000, 0], [2048, 952], [1, 2047, 0, 1500, 452]]


@pytest.mark.parametrize("threads", ["1", "2", "3"])
@pytest.mark.parametrize("split", SPLITS, ids=str)
@pytest.mark.parametrize("moments", MOMENTS)
def test_a_step_on_texture_samples_is_the_step_on_their_built_gradient_bit_for_bit(
    monkeypatch, threads, split, moments
):
    """``texture_samples`` builds each texel's gradient as the update reaches it from the
    lookups' segments as recorded (``split``: their lengths — one, several, empty ones, on
    and off the kernel's 2048-sample chunks): the tables, step counts, reports and journal
    are those of a step on the coalesced gradient ``TextureGather.gradient`` builds from
    the same lookups (a NaN output gradient in the second step rejects the texels it
    reaches)."""
    monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
    g = torch.Generator().manual_seed(5)
    start = torch.randn(40, 56, C, generator=g)
    built, sampled = start.clone(), start.clone()
    opts = (
        SparseAdam([built], lr=LR, moments=moments),
        SparseAdam([sampled], lr=LR, moments=moments),
    )
    journals = RowJournal(40 * 56, C, moments), RowJournal(40 * 56, C, moments)
    for it in range(3):
        uv, v_out = lookups(g, sum(split), C)
        if it == 1:
            v_out[100, 2] = float("nan")
        gather, recorded = TextureGather(built), TextureGather(sampled)
        for segment in zip(uv.split(split), v_out.split(split), strict=True):
            gather.record(*segment)
            recorded.record(*segment)
        built.grad = gather.gradient()
        expected = opts[0].step_reported(journals[0])
        built.grad = None
        report = opts[1].step_reported(journals[1], recorded.samples())
        assert torch.equal(report.peaks, expected.peaks)
        assert (report.rejected_rows, report.non_finite_rows) == (
            expected.rejected_rows,
            expected.non_finite_rows,
        )
        assert report.rejected_rows == (4 if it == 1 else 0)
        for name in ("exp_avg", "exp_avg_sq", "steps"):
            assert torch.equal(opts[1].state[sampled][name], opts[0].state[built][name])
        assert torch.equal(sampled, built)
        assert len(journals[1]) == len(journals[0]) > 0
    state = opts[1].state[sampled]
    journals[1].restore(
        sampled.reshape(-1, C).numpy(),
        moment_array(state["exp_avg"].reshape(-1, C)),
        moment_array(state["exp_avg_sq"].reshape(-1, C)),
        state["steps"].numpy(),
    )
    assert torch.equal(sampled, start)


def test_texture_samples_are_checked():
    p = torch.zeros(4, 4, 3)
    uv, v_out = torch.rand(10, 2), torch.ones(10, 3)
    opt = SparseAdam([p], lr=0.1)
    with pytest.raises(ShapeError, match=r"segment 1 must be uv \(M, 2\) and v_out \(M, 3\)"):
        opt.step_reported(None, [(uv, v_out), (uv, torch.ones(10, 4))])
    with pytest.raises(ShapeError, match=r"segment 0 .* got \(10, 2\) and \(9, 3\)"):
        opt.step_reported(None, [(uv, v_out[:9])])
    with pytest.raises(InvalidArgumentError, match=r"list of \(uv, v_out\) segments"):
        opt.step_reported(None, (uv, v_out))  # one pair, not a list of them
    with pytest.raises(ShapeError, match="texture"):
        flat = torch.zeros(16, 3)
        SparseAdam([flat], lr=0.1).step_reported(None, [(uv, v_out)])
    with pytest.raises(DTypeError, match=r"float32.* segment 1"):
        opt.step_reported(None, [(uv, v_out), (uv.double(), v_out)])
    p.grad = torch.ones(4, 4, 3)
    with pytest.raises(InvalidArgumentError, match="not both"):
        opt.step_reported(None, [(uv, v_out)])
    assert torch.equal(p, torch.zeros(4, 4, 3))


# --- NUMERICS.md case 33: bfloat16 moments --------------------------------------------


def test_case33_bfloat16_second_moments_decay_as_exact_ones(stability):
    """After a burst of unit gradients, 2000 steps of (numerically) zero gradient: the
    stored bfloat16 ``v`` decays as the exact float64 ``v`` does, on average over the
    texels, where ``v`` rounded to nearest would not decay at all (``0.999·v`` rounds back
    to ``v``: shown on the burst's own ``v``)."""
    p = torch.zeros(64, 56)
    opt = SparseAdam([p], lr=1e-3, moments="bfloat16")
    for _ in range(10):
        p.grad = torch.ones(64, 56)
        opt.step()
    v_burst = opt.state[p]["exp_avg_sq"].clone()
    assert torch.equal((0.999 * v_burst.float()).bfloat16(), v_burst)  # nearest: stuck
    for _ in range(2000):
        p.grad = torch.full((64, 56), 1e-30)  # touched, g² underflows to 0
        opt.step()
    exact = (1 - 0.999**10) * 0.999**2000
    mean = opt.state[p]["exp_avg_sq"].double().mean().item()
    stability.record(
        33,
        "bfloat16 v after 2000 zero-gradient steps: |mean / exact − 1|",
        abs(mean / exact - 1),
        0.01,
    )
    # Each stochastic rounding adds relative noise of std ≤ half bfloat16's relative
    # spacing (2⁻⁷ at most), and a pure decay does not damp relative noise: ≤ √2000·2⁻⁸.
    spread = (opt.state[p]["exp_avg_sq"].double() / exact - 1).std().item()
    stability.record(
        33, "bfloat16 v over the texels: std of v / exact − 1", spread, 2000**0.5 / 256
    )


def test_case33_bfloat16_steps_follow_the_float64_reference(stability):
    """A noisy quadratic over 300 steps of sparse gradients spanning 1e-6 to 1e2: the
    parameters with bfloat16 moments stay as close to the float64 reference as float32
    moments' do, relative to how far the parameters moved."""
    g = torch.Generator().manual_seed(7)
    start = torch.randn(H * W, C, generator=g)
    target = torch.randn(H * W, C, generator=g)
    scale = torch.tensor([1e-6, 1e-3, 1.0, 1e2, 1e-2])
    params = {moments: start.clone() for moments in MOMENTS}
    opts = {moments: SparseAdam([params[moments]], lr=LR, moments=moments) for moments in MOMENTS}
    expect = start.clone()
    m, v = torch.zeros_like(expect), torch.zeros_like(expect)
    steps = torch.zeros(H * W, dtype=torch.int64)
    for _ in range(300):
        rows = torch.randperm(H * W, generator=g)[:100].sort().values
        noise = torch.randn(100, C, generator=g)
        grads = ((expect[rows] - target[rows]) + 0.3 * noise) * scale
        for moments in MOMENTS:
            param = params[moments]
            param.grad = torch.zeros_like(param).index_put((rows,), grads)
            opts[moments].step()
        ref.sparse_adam_step(expect, m, v, steps, rows, grads, LR, 0.9, 0.999, 1e-15)
    moved = (expect - start).abs().amax(0)  # (C,)
    errors = {k: ((p - expect).abs().amax(0) / moved).max().item() for k, p in params.items()}
    stability.record(
        33, "bfloat16 moments: max |p − p_ref| / max |p_ref − p_0|", errors["bfloat16"], 0.05
    )
    stability.record(33, "float32 moments, the same", errors["float32"], 1e-4)


def test_moment_kinds_are_checked_and_a_state_loads_into_either():
    p = torch.zeros(4, 4, 3)
    with pytest.raises(InvalidArgumentError, match="moments must be one of"):
        SparseAdam([p], moments="float16")
    with pytest.raises(InvalidArgumentError, match="moments must be"):
        RowJournal(16, 3, "float64")
    opt = SparseAdam([p], lr=0.1, moments="bfloat16")
    p.grad = torch.ones(4, 4, 3)
    opt.step()
    state = opt.state[p]
    assert state["exp_avg"].dtype == state["exp_avg_sq"].dtype == torch.bfloat16
    with pytest.raises(InvalidArgumentError, match="journal keeps moments of the other kind"):
        opt.step_reported(RowJournal(16, 3, "float32"))
    widened = SparseAdam([p], lr=0.1)  # float32 moments: bfloat16 ones widen exactly
    widened.load_state_dict(opt.state_dict())
    assert widened.state[p]["exp_avg_sq"].dtype == torch.float32
    assert torch.equal(widened.state[p]["exp_avg_sq"], state["exp_avg_sq"].float())
    narrowed = SparseAdam([p], lr=0.1, moments="bfloat16")
    narrowed.load_state_dict(widened.state_dict())
    assert torch.equal(narrowed.state[p]["exp_avg"], state["exp_avg"])


def test_bfloat16_first_moments_round_as_torch_converts():
    """The first step stores m = (1 − β1)·g rounded to nearest: bit for bit torch's own
    float32 → bfloat16 conversion, over gradients spanning 1e-30 to 1e30."""
    g = torch.Generator().manual_seed(11)
    p = torch.zeros(100, 100)
    grad = torch.randn(100, 100, generator=g) * 10.0 ** torch.randint(
        -30, 30, (100, 100), generator=g
    )
    p.grad = grad
    opt = SparseAdam([p], lr=0.1, moments="bfloat16")
    opt.step()
    expected = (torch.tensor(1 - 0.9, dtype=torch.float32) * grad).bfloat16()
    assert torch.equal(opt.state[p]["exp_avg"].view(torch.int16), expected.view(torch.int16))
