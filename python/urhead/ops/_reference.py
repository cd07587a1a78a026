"""Plain-PyTorch references for every kernel, float64-capable, written for clarity rather
than speed. Tests compare the Rust kernels (forward and autograd gradients) against these."""

from __future__ import annotations

import torch

from urhead.ops.lbs import LbsOutput


def hat(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) → (..., 3, 3) cross-product matrices."""
    z = torch.zeros_like(w[..., 0])
    x, y, zc = w.unbind(-1)
    return torch.stack(
        [torch.stack([z, -zc, y], -1), torch.stack([zc, z, -x], -1), torch.stack([-y, x, z], -1)],
        -2,
    )


def axis_angle_to_matrix(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle → (..., 3, 3), Taylor series below θ = 1e-2 (NUMERICS.md)."""
    theta_sq = (w * w).sum(-1)[..., None, None]
    small = theta_sq < 1e-4
    safe_sq = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta = safe_sq.sqrt()
    a = torch.where(small, 1 - theta_sq / 6 + theta_sq**2 / 120, torch.sin(theta) / theta)
    b = torch.where(
        small, 0.5 - theta_sq / 24 + theta_sq**2 / 720, (1 - torch.cos(theta)) / safe_sq
    )
    k = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def lbs(
    betas, pose, v_template, shapedirs, posedirs, j_regressor, parents, lbs_weights, transl=None
) -> LbsOutput:
    """Reference of :func:`urhead.ops.lbs` (same arguments and outputs)."""
    batch = betas.shape[0]
    num_joints = j_regressor.shape[0]
    v_shaped = v_template + torch.einsum("bl,vcl->bvc", betas, shapedirs)
    rest_joints = torch.einsum("jv,bvc->bjc", j_regressor, v_shaped)
    rots = axis_angle_to_matrix(pose.reshape(batch, num_joints, 3))
    eye = torch.eye(3, dtype=betas.dtype)
    pose_feats = (rots[:, 1:] - eye).reshape(batch, -1)
    v_posed = v_shaped + (pose_feats @ posedirs).reshape(batch, -1, 3)

    parents = [int(p) for p in parents]
    globals_r, globals_t = [], []
    for j in range(num_joints):
        if j == 0:
            globals_r.append(rots[:, 0])
            globals_t.append(rest_joints[:, 0])
        else:
            p = parents[j]
            rel = rest_joints[:, j] - rest_joints[:, p]
            globals_r.append(globals_r[p] @ rots[:, j])
            globals_t.append(globals_t[p] + (globals_r[p] @ rel[..., None])[..., 0])
    g_r = torch.stack(globals_r, 1)
    g_t = torch.stack(globals_t, 1)
    a_t = g_t - (g_r @ rest_joints[..., None])[..., 0]
    blend_r = torch.einsum("vj,bjrc->bvrc", lbs_weights, g_r)
    blend_t = torch.einsum("vj,bjr->bvr", lbs_weights, a_t)
    verts = (blend_r @ v_posed[..., None])[..., 0] + blend_t
    joints = g_t
    if transl is not None:
        verts = verts + transl[:, None]
        joints = joints + transl[:, None]
    return LbsOutput(verts, joints, blend_r)


def sparse_adam_step(param, exp_avg, exp_avg_sq, steps, rows, grads, lr, beta1, beta2, eps):
    """Reference of :class:`urhead.optim.SparseAdam`'s update, in place on (N, C) tables:
    lazy Adam with per-row step counts; rows with a non-finite gradient are skipped."""
    bound = max(1.0, (1 - beta1) / (1 - beta2) ** 0.5)
    for k, row in enumerate(rows.tolist()):
        g = grads[k].double()
        if not torch.isfinite(g).all():
            continue
        steps[row] += 1
        t = int(steps[row])
        m = beta1 * exp_avg[row].double() + (1 - beta1) * g
        v = beta2 * exp_avg_sq[row].double() + (1 - beta2) * g * g
        step = (m / (1 - beta1**t)) / ((v / (1 - beta2**t)).sqrt() + eps)
        param[row] = param[row] - step.clamp(-bound, bound) * lr.double()
        exp_avg[row] = m
        exp_avg_sq[row] = v
