"""urhead.ops.lbs against the plain-torch reference, finite differences, and NUMERICS.md
cases 22–24 (Rodrigues and skinning extremes), 26 (bad input) and 27 (determinism)."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import make_skinned_model
from urhead.ops import _reference as ref
from urhead.ops import lbs
from urhead.ops._reference import hat

B = 3


def inputs(model, batch=B, pose_scale=0.5, seed=1, requires_grad=True):
    g = torch.Generator().manual_seed(seed)
    dtype = model.v_template.dtype
    nb = model.shapedirs.shape[2]
    nj = model.j_regressor.shape[0]
    betas = (torch.randn(batch, nb, generator=g, dtype=torch.float64)).to(dtype)
    pose = (torch.randn(batch, nj * 3, generator=g, dtype=torch.float64) * pose_scale).to(dtype)
    transl = (torch.randn(batch, 3, generator=g, dtype=torch.float64) * 0.1).to(dtype)
    return [t.requires_grad_(requires_grad) for t in (betas, pose, transl)]


def weighted_loss(out, seed=2):
    g = torch.Generator().manual_seed(seed)
    total = 0
    for t in out:
        w = torch.randn(t.shape, generator=g, dtype=torch.float64).to(t.dtype)
        total = total + (t * w).sum()
    return total


def rel_err(a, b):
    return ((a - b).norm() / b.norm().clamp_min(1e-30)).item()


@pytest.mark.parametrize("pose_scale", [0.5, 3.0])
def test_forward_and_gradients_match_reference_float64(model64, pose_scale):
    v_template = model64.v_template.clone().requires_grad_()
    shapedirs = model64.shapedirs.clone().requires_grad_()
    betas, pose, transl = inputs(model64, pose_scale=pose_scale)
    args = (betas, pose, v_template, shapedirs, *model64.tables()[2:])
    out = lbs(*args, transl=transl)
    expect = ref.lbs(*args, transl=transl)
    for a, b in zip(out, expect, strict=True):
        assert rel_err(a, b) < 1e-13
    wrt = (betas, pose, transl, v_template, shapedirs)
    grads = torch.autograd.grad(weighted_loss(out), wrt)
    expect_grads = torch.autograd.grad(weighted_loss(expect), wrt)
    for name, a, b in zip(
        ("betas", "pose", "transl", "v_template", "shapedirs"), grads, expect_grads, strict=True
    ):
        assert rel_err(a, b) < 1e-12, name


def test_float32_matches_float64_reference():
    m32 = make_skinned_model(num_verts=5023, num_betas=400, dtype=torch.float32, seed=3)
    m64 = make_skinned_model(num_verts=5023, num_betas=400, dtype=torch.float64, seed=3)
    b32 = inputs(m32, batch=2, seed=4)
    b64 = inputs(m64, batch=2, seed=4)
    out = lbs(b32[0], b32[1], *m32.tables(), transl=b32[2])
    expect = ref.lbs(b64[0], b64[1], *m64.tables(), transl=b64[2])
    for a, b in zip(out, expect, strict=True):
        assert rel_err(a.double(), b) < 1e-5
    grads = torch.autograd.grad(weighted_loss(out), b32)
    expect_grads = torch.autograd.grad(weighted_loss(expect), b64)
    for name, a, b in zip(("betas", "pose", "transl"), grads, expect_grads, strict=True):
        assert rel_err(a.double(), b) < 1e-4, name


def test_gradcheck_finite_differences():
    m = make_skinned_model(num_verts=40, num_betas=6, seed=5)
    betas, pose, transl = inputs(m, batch=2, pose_scale=1.5)
    v_template = m.v_template.clone().requires_grad_()
    shapedirs = m.shapedirs.clone().requires_grad_()

    def fn(betas, pose, transl, v_template, shapedirs):
        return tuple(lbs(betas, pose, v_template, shapedirs, *m.tables()[2:], transl=transl))

    assert torch.autograd.gradcheck(
        fn, (betas, pose, transl, v_template, shapedirs), eps=1e-6, atol=1e-8, rtol=1e-6
    )


def test_only_requested_gradients_are_computed(model64):
    betas, pose, transl = inputs(model64)
    betas.requires_grad_(False)
    out = lbs(betas, pose, *model64.tables(), transl=transl)
    out.verts.sum().backward()
    assert betas.grad is None and pose.grad is not None and transl.grad is not None
    # the joints alone still reach pose through the chain
    pose.grad = None
    lbs(betas, pose, *model64.tables()).joints.sum().backward()
    assert pose.grad.abs().sum() > 0


def single_joint_model(dtype=torch.float64):
    """Every vertex fully on the root: the rotations output is R(ω_root) itself."""
    m = make_skinned_model(num_verts=8, num_betas=2, dtype=dtype, seed=6)
    m.lbs_weights = torch.zeros_like(m.lbs_weights)
    m.lbs_weights[:, 0] = 1
    return m


def root_rotation(m, omega):
    pose = torch.zeros(1, 15, dtype=omega.dtype)
    pose[0, :3] = omega
    betas = torch.zeros(1, m.shapedirs.shape[2], dtype=omega.dtype)
    return lbs(betas, pose, *m.tables()).rotations[0, 0]


OMEGA_AXIS = torch.tensor([0.36, -0.48, 0.8], dtype=torch.float64)


@pytest.mark.parametrize("theta", [0.0, 1e-12, 1e-8, 1e-4, 2.4e-4, 1e-2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_case22_small_angles(theta, dtype):
    m = single_joint_model(dtype)
    omega = OMEGA_AXIS * theta
    rot = root_rotation(m, omega.to(dtype)).double()
    eye = torch.eye(3, dtype=torch.float64)
    tol = 1e-6 if dtype == torch.float32 else 1e-15
    assert (rot.T @ rot - eye).abs().max() < tol
    k = hat(omega)
    second_order = eye + k + k @ k / 2  # exact to θ³, which is below f64 resolution here
    assert (rot - ref.axis_angle_to_matrix(omega)).abs().max() < tol
    if theta <= 1e-4:
        assert (rot - second_order).abs().max() < max(tol, theta**3)


def test_case22_negative_tiny_and_generator_at_zero():
    m = single_joint_model()
    omega = torch.full((3,), -1e-8, dtype=torch.float64)
    assert (root_rotation(m, omega) - ref.axis_angle_to_matrix(omega)).abs().max() < 1e-16
    jac = torch.autograd.functional.jacobian(
        lambda w: root_rotation(m, w), torch.zeros(3, dtype=torch.float64)
    )
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = 1
        assert torch.equal(jac[..., k], hat(e))


@pytest.mark.parametrize("theta", [1e-4, 2.4e-4, 9.99e-3, 1.001e-2, 0.3])
def test_case22_gradients_finite_differences_near_taylor_switch(theta):
    m = single_joint_model()
    omega = (OMEGA_AXIS * theta).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda w: root_rotation(m, w), (omega,), eps=1e-7, atol=1e-9, rtol=1e-6
    )


@pytest.mark.parametrize("theta", [math.pi - 1e-6, math.pi + 1e-6, 2 * math.pi, 10 * math.pi])
def test_case23_large_angles_finite_and_match_reference(theta):
    m = single_joint_model()
    omega = (OMEGA_AXIS * theta).requires_grad_()
    rot = root_rotation(m, omega)
    assert torch.isfinite(rot).all()
    assert (rot - ref.axis_angle_to_matrix(omega)).abs().max() < 1e-14
    (grad,) = torch.autograd.grad(rot.sum(), omega)
    (expect,) = torch.autograd.grad(ref.axis_angle_to_matrix(omega).sum(), omega)
    assert torch.isfinite(grad).all()
    assert (grad - expect).abs().max() < 1e-12


def test_case24_zero_pose_gives_shaped_template():
    m = make_skinned_model(dyadic_weights=True, seed=7)
    betas = torch.zeros(1, m.shapedirs.shape[2], dtype=torch.float64)
    pose = torch.zeros(1, 15, dtype=torch.float64)
    out = lbs(betas, pose, *m.tables())
    assert torch.equal(out.verts[0], m.v_template)  # bit for bit
    betas = torch.randn(1, m.shapedirs.shape[2], dtype=torch.float64)
    out = lbs(betas, pose, *m.tables())
    shaped = m.v_template + torch.einsum("l,vcl->vc", betas[0], m.shapedirs)
    assert (out.verts[0] - shaped).abs().max() < 1e-15


def test_case24_large_poses_on_all_joints():
    m32 = make_skinned_model(dtype=torch.float32, seed=8)
    m64 = make_skinned_model(dtype=torch.float64, seed=8)
    b64 = inputs(m64, batch=4, pose_scale=4.0, seed=9, requires_grad=False)
    b32 = [t.float() for t in b64]
    out = lbs(b32[0], b32[1], *m32.tables(), transl=b32[2])
    expect = ref.lbs(b64[0], b64[1], *m64.tables(), transl=b64[2])
    assert (out.verts.double() - expect.verts).abs().max() < 1e-6
    assert (out.joints.double() - expect.joints).abs().max() < 1e-6
