"""NUMERICS.md cases 26 (bad input gives a clear error naming the argument, before any
work) and 27 (bitwise determinism across thread counts), plus fork and thread safety."""

from __future__ import annotations

import multiprocessing as mp
import os
import threading

import pytest
import torch

from conftest import make_skinned_model
from urhead.errors import (
    DTypeError,
    InvalidArgumentError,
    NonFiniteError,
    ShapeError,
)
from urhead.ops import lbs


def call(m, betas=None, pose=None, transl=None, **tables):
    t = dict(
        zip(
            ("v_template", "shapedirs", "posedirs", "j_regressor", "parents", "lbs_weights"),
            m.tables(),
            strict=True,
        )
    )
    t.update(tables)
    dtype = m.v_template.dtype
    betas = torch.zeros(2, m.shapedirs.shape[2], dtype=dtype) if betas is None else betas
    pose = torch.zeros(2, 15, dtype=dtype) if pose is None else pose
    return lbs(betas, pose, transl=transl, **t)


@pytest.fixture
def m():
    return make_skinned_model(num_verts=30, num_betas=4, dtype=torch.float32)


@pytest.mark.parametrize("arg", ["betas", "pose", "transl"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_per_call_inputs_are_named(m, arg, bad, stability):
    kwargs = {"betas": torch.zeros(2, 4), "pose": torch.zeros(2, 15), "transl": torch.zeros(2, 3)}
    kwargs[arg][1, 1] = bad
    with pytest.raises(NonFiniteError, match=f"^{arg} must be finite"):
        call(m, **kwargs)
    stability.checked(26, "skinning: NaN/±inf in betas, pose, transl → NonFiniteError naming it")


@pytest.mark.parametrize(
    "arg", ["v_template", "shapedirs", "posedirs", "j_regressor", "lbs_weights"]
)
def test_non_finite_model_tables_are_named(m, arg, stability):
    table = getattr(m, arg).clone()
    table.view(-1)[5] = float("nan")
    with pytest.raises(NonFiniteError, match=f"^{arg} must be finite"):
        call(m, betas=torch.ones(2, 4), pose=torch.full((2, 15), 0.1), **{arg: table})
    stability.checked(26, "skinning: NaN in a model table → NonFiniteError naming it")


@pytest.mark.parametrize(
    ("arg", "value", "pattern"),
    [
        ("betas", torch.zeros(2, 5), r"betas must be \(B, NB\) = \(2, 4\)"),
        ("betas", torch.zeros(4), "betas must be"),
        ("pose", torch.zeros(2, 12), "pose must be"),
        ("pose", torch.zeros(3, 15), "pose must have batch size"),
        ("transl", torch.zeros(2, 2), "transl must be"),
        ("v_template", torch.zeros(29, 3), "shapedirs must be"),
        ("shapedirs", torch.zeros(30, 3), "shapedirs must be"),
        ("posedirs", torch.zeros(36, 89), "posedirs must be"),
        ("j_regressor", torch.zeros(5, 31), "v_template must be|j_regressor must be"),
        ("lbs_weights", torch.zeros(30, 4), "lbs_weights must be"),
        ("parents", torch.tensor([-1, 0, 1, 1], dtype=torch.int32), "parents must be"),
    ],
)
def test_wrong_shapes_are_named(m, arg, value, pattern, stability):
    with pytest.raises(ShapeError, match=pattern):
        call(m, **{arg: value})
    stability.checked(26, "skinning: wrong shapes → ShapeError naming the argument")


def test_empty_mesh_is_rejected(m, stability):
    with pytest.raises(ShapeError, match="v_template"):
        call(
            m,
            v_template=torch.zeros(0, 3),
            shapedirs=torch.zeros(0, 3, 4),
            posedirs=torch.zeros(36, 0),
            j_regressor=torch.zeros(5, 0),
            lbs_weights=torch.zeros(0, 5),
        )
    stability.checked(26, "skinning: empty mesh → ShapeError naming v_template")


@pytest.mark.parametrize("parents", [[0, 0, 1, 1, 1], [-1, 0, 3, 1, 1], [-1, 0, 1, 1, 9]])
def test_parents_must_be_a_topological_tree(m, parents):
    with pytest.raises(InvalidArgumentError, match="parents"):
        call(m, parents=torch.tensor(parents))


def test_dtype_device_and_layout_errors(m, stability):
    with pytest.raises(DTypeError, match="betas must be float32 or float64"):
        call(m, betas=torch.zeros(2, 4, dtype=torch.int64))
    with pytest.raises(DTypeError, match=r"pose must be torch\.float32"):
        call(m, pose=torch.zeros(2, 15, dtype=torch.float64))
    with pytest.raises(DTypeError, match=r"shapedirs must be a torch\.Tensor"):
        call(m, shapedirs=m.shapedirs.numpy())
    with pytest.raises(InvalidArgumentError, match="pose must be contiguous"):
        call(m, pose=torch.zeros(15, 2).T)
    stability.checked(26, "skinning: wrong dtype, type, non-contiguous → named error", 4)


def test_sparse_regressor_is_accepted(m):
    betas = torch.randn(2, 4)
    dense = call(m, betas=betas).verts
    sparse = call(m, betas=betas, j_regressor=m.j_regressor.to_sparse()).verts
    assert torch.equal(dense, sparse)


def run_with_threads(n, fn):
    old = os.environ.get("URHEAD_NUM_THREADS")
    os.environ["URHEAD_NUM_THREADS"] = str(n)
    try:
        return fn()
    finally:
        if old is None:
            del os.environ["URHEAD_NUM_THREADS"]
        else:
            os.environ["URHEAD_NUM_THREADS"] = old


def forward_backward(model):
    g = torch.Generator().manual_seed(0)
    betas = torch.randn(4, model.shapedirs.shape[2], generator=g).requires_grad_()
    pose = (torch.randn(4, 15, generator=g) * 0.7).requires_grad_()
    transl = torch.randn(4, 3, generator=g).requires_grad_()
    out = lbs(betas, pose, *model.tables(), transl=transl)
    w = torch.randn(out.verts.shape, generator=g)
    (out.verts * w).sum().backward()
    return [out.verts, out.joints, out.rotations, betas.grad, pose.grad, transl.grad]


def test_case27_bitwise_identical_across_thread_counts(stability):
    model = make_skinned_model(num_verts=5023, num_betas=100, dtype=torch.float32, seed=11)
    baseline = run_with_threads(1, lambda: forward_backward(model))
    for n in (1, 2, 3, 8):
        for _ in range(10 if n == 2 else 2):
            result = run_with_threads(n, lambda: forward_backward(model))
            for a, b in zip(result, baseline, strict=True):
                differing = (a != b).sum()
                stability.record(
                    27, "skinning: elements differing from the 1-thread run", differing, 0
                )
                assert torch.equal(a, b), f"{n} threads"


def test_bad_thread_setting_is_named():
    with pytest.raises(InvalidArgumentError, match="URHEAD_NUM_THREADS"):
        run_with_threads("zero", lambda: call(make_skinned_model(dtype=torch.float32)))


def _child(queue):
    # torch's own OpenMP pool can deadlock in a forked child; keep torch single-threaded
    # there while urhead's pool still runs two workers.
    torch.set_num_threads(1)
    os.environ["URHEAD_NUM_THREADS"] = "2"
    model = make_skinned_model(num_verts=500, dtype=torch.float32, seed=12)
    queue.put([t.tolist() for t in forward_backward(model)[:2]])


def test_safe_after_fork():
    model = make_skinned_model(num_verts=500, dtype=torch.float32, seed=12)
    parent = forward_backward(model)  # spins up the parent's thread pool first
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child, args=(queue,))
    proc.start()
    child = queue.get(timeout=60)
    proc.join(timeout=60)
    assert proc.exitcode == 0
    for a, b in zip(child, parent[:2], strict=True):
        assert torch.equal(torch.tensor(a), b)


def test_concurrent_calls_from_python_threads():
    model = make_skinned_model(num_verts=2000, dtype=torch.float32, seed=13)
    expect = forward_backward(model)
    results = []

    def work():
        results.append(forward_backward(model))

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 4
    for r in results:
        for a, b in zip(r, expect, strict=True):
            assert torch.equal(a, b)
