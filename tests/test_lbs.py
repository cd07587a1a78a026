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
def test_case22_small_angles(theta, dtype, stability):
    m = single_joint_model(dtype)
    omega = OMEGA_AXIS * theta
    rot = root_rotation(m, omega.to(dtype)).double()
    eye = torch.eye(3, dtype=torch.float64)
    tol = 1e-6 if dtype == torch.float32 else 1e-15
    name = str(dtype)[6:]
    ortho_err = (rot.T @ rot - eye).abs().max()
    stability.record(22, f"max abs RᵀR − I ({name})", ortho_err, tol)
    assert (rot.T @ rot - eye).abs().max() < tol
    k = hat(omega)
    second_order = eye + k + k @ k / 2  # exact to θ³, which is below f64 resolution here
    ref_err = (rot - ref.axis_angle_to_matrix(omega)).abs().max()
    stability.record(22, f"max abs R error vs float64 reference ({name})", ref_err, tol)
    assert (rot - ref.axis_angle_to_matrix(omega)).abs().max() < tol
    if theta <= 1e-4:
        second_err = (rot - second_order).abs().max()
        bound = max(tol, theta**3)
        stability.record(22, f"θ ≤ 1e-4: max abs R − (I + K + K²/2) ({name})", second_err, bound)
        assert (rot - second_order).abs().max() < max(tol, theta**3)


def test_case22_negative_tiny_and_generator_at_zero(stability):
    m = single_joint_model()
    omega = torch.full((3,), -1e-8, dtype=torch.float64)
    err = (root_rotation(m, omega) - ref.axis_angle_to_matrix(omega)).abs().max()
    stability.record(22, "ω = −1e-8·(1, 1, 1): max abs R error vs reference", err, 1e-16)
    assert (root_rotation(m, omega) - ref.axis_angle_to_matrix(omega)).abs().max() < 1e-16
    jac = torch.autograd.functional.jacobian(
        lambda w: root_rotation(m, w), torch.zeros(3, dtype=torch.float64)
    )
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = 1
        stability.record(
            22, "ω = 0: max abs dR/dω_k − hat(e_k)", (jac[..., k] - hat(e)).abs().max(), 0
        )
        assert torch.equal(jac[..., k], hat(e))


@pytest.mark.parametrize("theta", [1e-4, 2.4e-4, 9.99e-3, 1.001e-2, 0.3])
def test_case22_gradients_finite_differences_near_taylor_switch(theta, stability):
    m = single_joint_model()
    omega = (OMEGA_AXIS * theta).requires_grad_()
    # The figure gradcheck tests: analytic Jacobian vs central differences with its eps.
    jac = torch.autograd.functional.jacobian(lambda w: root_rotation(m, w), omega.detach())
    steps = torch.eye(3, dtype=torch.float64) * 1e-7
    fd = torch.stack(
        [(root_rotation(m, omega + s) - root_rotation(m, omega - s)) / 2e-7 for s in steps], -1
    ).detach()
    stability.close(
        22, "Jacobian vs central differences near the Taylor switch", jac, fd, 1e-6, 1e-9
    )
    assert torch.autograd.gradcheck(
        lambda w: root_rotation(m, w), (omega,), eps=1e-7, atol=1e-9, rtol=1e-6
    )


@pytest.mark.parametrize("theta", [math.pi - 1e-6, math.pi + 1e-6, 2 * math.pi, 10 * math.pi])
def test_case23_large_angles_finite_and_match_reference(theta, stability):
    m = single_joint_model()
    omega = (OMEGA_AXIS * theta).requires_grad_()
    rot = root_rotation(m, omega)
    assert torch.isfinite(rot).all()
    err = (rot - ref.axis_angle_to_matrix(omega)).abs().max()
    stability.record(23, "max abs R error vs float64 reference", err, 1e-14)
    assert (rot - ref.axis_angle_to_matrix(omega)).abs().max() < 1e-14
    (grad,) = torch.autograd.grad(rot.sum(), omega)
    (expect,) = torch.autograd.grad(ref.axis_angle_to_matrix(omega).sum(), omega)
    assert torch.isfinite(grad).all()
    stability.record(
        23, "max abs dR/dω error vs reference autograd", (grad - expect).abs().max(), 1e-12
    )
    assert (grad - expect).abs().max() < 1e-12


def test_case24_zero_pose_gives_shaped_template(stability):
    m = make_skinned_model(dyadic_weights=True, seed=7)
    betas = torch.zeros(1, m.shapedirs.shape[2], dtype=torch.float64)
    pose = torch.zeros(1, 15, dtype=torch.float64)
    out = lbs(betas, pose, *m.tables())
    exact_err = (out.verts[0] - m.v_template).abs().max()
    stability.record(24, "zero pose, zero betas: max abs vertex − template", exact_err, 0)
    assert torch.equal(out.verts[0], m.v_template)  # bit for bit
    betas = torch.randn(1, m.shapedirs.shape[2], dtype=torch.float64)
    out = lbs(betas, pose, *m.tables())
    shaped = m.v_template + torch.einsum("l,vcl->vc", betas[0], m.shapedirs)
    shaped_err = (out.verts[0] - shaped).abs().max()
    stability.record(24, "zero pose: max abs vertex − (template + blendshapes)", shaped_err, 1e-15)
    assert (out.verts[0] - shaped).abs().max() < 1e-15


def test_case24_large_poses_on_all_joints(stability):
    m32 = make_skinned_model(dtype=torch.float32, seed=8)
    m64 = make_skinned_model(dtype=torch.float64, seed=8)
    b64 = inputs(m64, batch=4, pose_scale=4.0, seed=9, requires_grad=False)
    b32 = [t.float() for t in b64]
    out = lbs(b32[0], b32[1], *m32.tables(), transl=b32[2])
    expect = ref.lbs(b64[0], b64[1], *m64.tables(), transl=b64[2])
    err = max(
        (out.verts.double() - expect.verts).abs().max(),
        (out.joints.double() - expect.joints).abs().max(),
    )
    stability.record(
        24, "large poses, float32: max abs vertex/joint error vs float64 reference", err, 1e-6
    )
    assert (out.verts.double() - expect.verts).abs().max() < 1e-6
    assert (out.joints.double() - expect.joints).abs().max() < 1e-6
    # Float64 gradients at the same poses against central differences, per input.
    leaves = [t.clone().requires_grad_(True) for t in b64]
    grads = torch.autograd.grad(
        weighted_loss(lbs(leaves[0], leaves[1], *m64.tables(), transl=leaves[2])), leaves
    )
    g = torch.Generator().manual_seed(10)
    h = 1e-6
    for k, name in enumerate(("shape and expression", "pose", "translation")):
        d = torch.randn(b64[k].shape, generator=g, dtype=torch.float64)

        def loss(t, k=k, d=d):
            args = list(b64)
            args[k] = b64[k] + t * d
            return float(weighted_loss(lbs(args[0], args[1], *m64.tables(), transl=args[2])))

        fd = (loss(h) - loss(-h)) / (2 * h)
        fd_err = abs(float((grads[k] * d).sum()) - fd) / max(1.0, abs(fd))
        stability.record(24, f"large poses: {name} gradient vs central differences", fd_err, 1e-8)
