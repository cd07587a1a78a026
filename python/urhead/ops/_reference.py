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


# --- Gaussian splatting --------------------------------------------------------------

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, 3) unit directions → (N, (degree+1)²) real SH basis (3DGS constants and signs)."""
    x, y, z = dirs.unbind(-1)
    b = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        b += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        b += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(b, -1)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) unit (w, x, y, z) → (N, 3, 3)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def project_gaussians(means, quats, scales, opacities, camera, sh=None, sh_degree=0):
    """Reference of the projection (gsplat classic EWA, clamped Jacobian, 0.3 px²
    dilation, opacity-aware radius). Returns (means2d (N,2), conics (N,3), depths (N,),
    radii (N,2) int32, colors (N,3) or None); culled Gaussians get zeros."""
    dtype = means.dtype
    n = means.shape[0]
    view = camera.viewmat.to(dtype)
    rot_w, trans = view[:3, :3], view[:3, 3]
    k = camera.K.to(dtype)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    width, height = camera.width, camera.height
    p_cam = means @ rot_w.T + trans
    z_all = p_cam[:, 2].detach()
    tiny = torch.finfo(dtype).tiny
    keep = (
        (z_all >= camera.near)
        & (z_all <= camera.far)
        & ((quats.detach() ** 2).sum(-1) > 0)
        & (scales.detach().abs() >= tiny).all(-1)
        & (opacities.detach() >= 1 / 255)
    )
    idx = keep.nonzero()[:, 0]
    pc = p_cam[idx]
    x, y, z = pc.unbind(-1)
    q = quats[idx] / quats[idx].norm(dim=-1, keepdim=True)
    m = quat_to_rotmat(q) * scales[idx][:, None, :]
    cov_cam = rot_w @ (m @ m.transpose(-1, -2)) @ rot_w.T
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    ux = torch.clamp(x / z, -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x)
    uy = torch.clamp(y / z, -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(z)
    jac = torch.stack(
        [
            torch.stack([fx / z, zero, -fx * ux / z], -1),
            torch.stack([zero, fy / z, -fy * uy / z], -1),
        ],
        -2,
    )
    cov2 = jac @ cov_cam @ jac.transpose(-1, -2)
    a, b, c = cov2[:, 0, 0] + 0.3, cov2[:, 0, 1], cov2[:, 1, 1] + 0.3
    det = a * c - b * b
    conic = torch.stack([c / det, -b / det, a / det], -1)
    mean2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    ext = torch.clamp(torch.sqrt(2 * torch.log(opacities[idx].detach() * 255)), max=3.33)
    radius = torch.stack(
        [torch.ceil(ext * a.detach().sqrt()), torch.ceil(ext * c.detach().sqrt())], -1
    )
    md = mean2d.detach()
    ok = (
        (det.detach() > 0)
        & torch.isfinite(det.detach())
        & (radius > 0).all(-1)
        & (md[:, 0] + radius[:, 0] > 0)
        & (md[:, 0] - radius[:, 0] < width)
        & (md[:, 1] + radius[:, 1] > 0)
        & (md[:, 1] - radius[:, 1] < height)
    )
    sel = idx[ok]
    means2d = torch.zeros(n, 2, dtype=dtype).index_copy(0, sel, mean2d[ok])
    conics = torch.zeros(n, 3, dtype=dtype).index_copy(0, sel, conic[ok])
    depths = torch.zeros(n, dtype=dtype).index_copy(0, sel, z[ok].detach())
    radii = torch.zeros(n, 2, dtype=torch.int32).index_copy(0, sel, radius[ok].to(torch.int32))
    colors = None
    if sh is not None:
        centre = -rot_w.T @ trans
        d = means[sel] - centre
        dirs = d / d.norm(dim=-1, keepdim=True)
        basis = sh_basis(dirs, sh_degree)
        raw = torch.einsum("nk,nkc->nc", basis, sh[sel][:, : basis.shape[1]]) + 0.5
        colors = torch.zeros(n, 3, dtype=dtype).index_copy(0, sel, torch.clamp(raw, min=0.0))
    return means2d, conics, depths, radii, colors


def composite_gaussians(
    means2d,
    conics,
    colors,
    opacities,
    depths,
    radii,
    width,
    height,
    background=None,
    depth_map=None,
    depth_eps=0.01,
):
    """Brute-force untiled front-to-back compositing over every pixel, Gaussians in
    (depth, index) order, with the same rules as the kernel (α = min(0.99, o·g), skip
    σ < 0 and α < 1/255, skip occluded samples, stop before T < 1e-4). Returns
    (image (H,W,C), transmittance (H,W), every T_i as (M, H, W) for the M visible
    Gaussians in compositing order)."""
    dtype = means2d.dtype
    vis = ((radii > 0).all(-1) & (opacities.detach() >= 1 / 255)).nonzero()[:, 0]
    order = vis[torch.sort(depths[vis], stable=True).indices]
    px = torch.arange(width, dtype=dtype) + 0.5
    py = torch.arange(height, dtype=dtype) + 0.5
    t = torch.ones(height, width, dtype=dtype)
    active = torch.ones(height, width, dtype=torch.bool)
    acc = torch.zeros(height, width, colors.shape[1], dtype=dtype)
    limit = None if depth_map is None else depth_map + depth_eps
    all_t = []
    for i in order.tolist():
        dx = means2d[i, 0] - px[None, :]
        dy = means2d[i, 1] - py[:, None]
        a, b, c = conics[i]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp(opacities[i] * torch.exp(-sigma), max=0.99)
        valid = (sigma >= 0) & (alpha >= 1 / 255) & active
        if limit is not None:
            valid = valid & (depths[i] <= limit)
        next_t = t * (1 - alpha)
        stop = valid & (next_t < 1e-4)
        contrib = valid & ~stop
        weight = torch.where(contrib, alpha * t, torch.zeros_like(t))
        acc = acc + weight[..., None] * colors[i]
        t = torch.where(contrib, next_t, t)
        active = active & ~stop
        all_t.append(t)
    if background is not None:
        acc = acc + t[..., None] * background
    stacked = torch.stack(all_t) if all_t else torch.zeros(0, height, width, dtype=dtype)
    return acc, t, stacked


def rasterize_gaussians(
    means,
    quats,
    scales,
    opacities,
    colors,
    camera,
    background=None,
    depth_map=None,
    depth_eps=0.01,
    sh_degree=None,
):
    """Reference of :func:`urhead.ops.rasterize_gaussians`: (image, transmittance,
    means2d) with autograd through everything."""
    if colors.dim() == 3:
        degree = int(colors.shape[1] ** 0.5) - 1 if sh_degree is None else sh_degree
        means2d, conics, depths, radii, rgb = project_gaussians(
            means, quats, scales, opacities, camera, colors, degree
        )
    else:
        means2d, conics, depths, radii, _ = project_gaussians(
            means, quats, scales, opacities, camera
        )
        rgb = colors
    image, t, _ = composite_gaussians(
        means2d,
        conics,
        rgb,
        opacities,
        depths,
        radii,
        camera.width,
        camera.height,
        background,
        depth_map,
        depth_eps,
    )
    return image, t, means2d
