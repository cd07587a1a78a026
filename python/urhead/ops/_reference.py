"""Plain-PyTorch references for every kernel, float64-capable, written for clarity rather
than speed. Tests compare the Rust kernels (forward and autograd gradients) against these."""

from __future__ import annotations

import math
from functools import lru_cache

import torch
import torch.nn.functional as F

from urhead.ops.lbs import LbsOutput
from urhead.sh import sh_basis


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


# --- Mesh rasterization (urhead.ops.rasterize / interpolate / texture / antialias) ---------

_SUBPIXEL = 256
_GUARD_BAND_PX = 16384.0


def _round_half_away(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.floor(x.abs() + 0.5)


def _homogeneous(verts: torch.Tensor, camera) -> torch.Tensor:
    """(V, 3) world → (V, 3) homogeneous screen positions (X, Y, W) = K·p_cam."""
    c = camera.world_to_camera(verts)
    k = camera.K.to(verts.dtype)
    return torch.stack(
        [k[0, 0] * c[:, 0] + k[0, 2] * c[:, 2], k[1, 1] * c[:, 1] + k[1, 2] * c[:, 2], c[:, 2]], -1
    )


def _pixel_centres(height: int, width: int, dtype) -> torch.Tensor:
    """(H·W, 3) homogeneous pixel centres (x + 0.5, y + 0.5, 1), row-major."""
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype) + 0.5,
        torch.arange(width, dtype=dtype) + 0.5,
        indexing="ij",
    )
    return torch.stack(
        [xs.reshape(-1), ys.reshape(-1), torch.ones(height * width, dtype=dtype)], -1
    )


def _raw_barycentrics(hom_tris: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """(F, 3, 3) triangles × (P, 3) pixels → (P, F, 3) unnormalised weights e·(h_j × h_k)."""
    h0, h1, h2 = hom_tris.unbind(1)
    normals = torch.stack(
        [torch.linalg.cross(h1, h2), torch.linalg.cross(h2, h0), torch.linalg.cross(h0, h1)], 1
    )
    return torch.einsum("pc,fkc->pfk", e, normals)


def _clamped(raw: torch.Tensor) -> torch.Tensor:
    """Normalise, clamp to the simplex, renormalise (the kernel's rule)."""
    lam = raw / raw.sum(-1, keepdim=True)
    lam = torch.where(lam > 0, lam, torch.zeros_like(lam))
    return lam / lam.sum(-1, keepdim=True)


def _snapped_coverage(hom_tris: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """(P, F) coverage of the triangles snapped to 1/256 px, top-left rule, exact integers."""
    xy = hom_tris[..., :2] / hom_tris[..., 2:]
    p = _round_half_away(xy.detach().double() * _SUBPIXEL).long()
    area2 = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (
        p[:, 2, 0] - p[:, 0, 0]
    )
    p = torch.where((area2 < 0)[:, None, None], p[:, [0, 2, 1]], p)
    s = (e[:, :2].double() * _SUBPIXEL).round().long()  # exact: centres are on the grid
    covered = (area2 != 0)[None, :].expand(e.shape[0], -1).clone()
    for k in range(3):
        a, b = p[:, k], p[:, (k + 1) % 3]
        dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        edge = dx[None] * (s[:, 1:2] - a[None, :, 1]) - dy[None] * (s[:, 0:1] - a[None, :, 0])
        top_left = (dy < 0) | ((dy == 0) & (dx > 0))
        covered &= (edge > 0) | ((edge == 0) & top_left[None])
    return covered


def _needs_clipping(hom_tris: torch.Tensor, width: int, height: int, near: float) -> torch.Tensor:
    x, y, w = hom_tris.detach().unbind(-1)
    g = _GUARD_BAND_PX
    inside = (
        (w >= near)
        & (x + g * w >= 0)
        & ((width + g) * w - x >= 0)
        & (y + g * w >= 0)
        & ((height + g) * w - y >= 0)
    )
    return ~inside.all(-1)


def _raster_homogeneous(hom, faces, height, width, near, far, chunk=256):
    """Brute-force raster of homogeneous triangles: (tri_id, bary, depth) with gradients
    flowing from ``hom`` into ``bary``.

    Triangles entirely inside the near plane and guard band use the kernel's snapped
    coverage exactly. Triangles that need clipping use exact geometry instead (weights all
    ≥ 0 and depth ≥ near), so they may differ from the kernel on pixels within a sub-pixel
    step of their edges.
    """
    f = faces.long()
    e = _pixel_centres(height, width, hom.dtype)
    best_depth = torch.full((e.shape[0],), float("inf"), dtype=torch.float64)
    best_tri = torch.full((e.shape[0],), -1, dtype=torch.int64)
    with torch.no_grad():
        for start in range(0, f.shape[0], chunk):
            tris = hom[f[start : start + chunk]].detach().double()
            raw = _raw_barycentrics(tris, e.double())
            lam = _clamped(raw)
            w = tris[None, :, :, 2]
            depth = (
                w[..., 0]
                + lam[..., 1] * (w[..., 1] - w[..., 0])
                + lam[..., 2] * (w[..., 2] - w[..., 0])
            )
            clip = _needs_clipping(tris, width, height, near)
            unclamped = raw / raw.sum(-1, keepdim=True)
            exact = (unclamped >= 0).all(-1) & (depth >= near)
            covered = torch.where(clip[None], exact, _snapped_coverage(tris, e.double()))
            covered &= torch.isfinite(lam).all(-1) & (depth <= far)
            depth = torch.where(covered, depth, torch.full_like(depth, float("inf")))
            # Lexicographic (depth, id) minimum: strictly nearer wins, ties keep the lower id.
            d_min, arg = depth.min(1)
            better = d_min < best_depth
            best_tri = torch.where(better, start + arg, best_tri)
            best_depth = torch.where(better, d_min, best_depth)
    covered = best_tri >= 0
    tri_safe = best_tri.clamp(min=0)
    tris = hom[f[tri_safe]]  # (P, 3, 3), differentiable
    h0, h1, h2 = tris.unbind(1)
    normals = torch.stack(
        [torch.linalg.cross(h1, h2), torch.linalg.cross(h2, h0), torch.linalg.cross(h0, h1)], 1
    )
    raw = torch.einsum("pc,pkc->pk", e, normals)
    lam = _clamped(torch.where(covered[:, None], raw, torch.ones_like(raw)))
    zero = torch.zeros_like(lam[:, 1:])
    bary = torch.where(covered[:, None], lam[:, 1:], zero).reshape(height, width, 2)
    depth = torch.where(covered, best_depth, torch.full_like(best_depth, float("inf")))
    tri_id = best_tri.to(torch.int32).reshape(height, width)
    return tri_id, bary, depth.to(hom.dtype).reshape(height, width)


def rasterize(verts, faces, camera):
    """Reference of :func:`urhead.ops.rasterize`: every triangle tested at every pixel."""
    from urhead.ops.rasterize import RasterOutput

    hom = _homogeneous(verts, camera)
    tri_id, bary, depth = _raster_homogeneous(
        hom, faces, camera.height, camera.width, camera.near, camera.far
    )
    return RasterOutput(tri_id, bary, depth)


def rasterize_uv(uv_coords, uv_faces, height, width):
    """Reference of :func:`urhead.ops.rasterize_uv`."""
    from urhead.ops.rasterize import UvRasterOutput

    u, v = uv_coords.unbind(-1)
    hom = torch.stack([u * width, (1 - v) * height, torch.ones_like(u)], -1)
    tri_id, bary, _ = _raster_homogeneous(hom, uv_faces, height, width, 0.0, float("inf"))
    return UvRasterOutput(tri_id, bary)


def interpolate(attr, raster, faces, pixels=None):
    """Reference of :func:`urhead.ops.interpolate`: the whole image, indexed at ``pixels``."""
    tri = raster.tri_id.long()
    covered = (tri >= 0)[..., None]
    f = faces.long()[tri.clamp(min=0)]
    b1, b2 = raster.bary.unbind(-1)
    b0 = 1 - b1 - b2
    out = (
        b0[..., None] * attr[f[..., 0]]
        + b1[..., None] * attr[f[..., 1]]
        + b2[..., None] * attr[f[..., 2]]
    )
    image = torch.where(covered, out, torch.zeros_like(out))
    return image if pixels is None else image.reshape(-1, attr.shape[-1])[pixels]


def texture(tex, uv):
    """Reference of :func:`urhead.ops.texture` (dense texture gradient)."""
    ht, wt, _ = tex.shape
    u, v = uv[..., 0], uv[..., 1]
    finite = torch.isfinite(u) & torch.isfinite(v)
    u = torch.where(finite, u, torch.zeros_like(u))
    v = torch.where(finite, v, torch.zeros_like(v))
    x = (u * wt - 0.5).clamp(-1, wt)
    y = ((1 - v) * ht - 0.5).clamp(-1, ht)
    x0, y0 = x.detach().floor(), y.detach().floor()
    fx, fy = x - x0, y - y0
    c0 = x0.long().clamp(0, wt - 1)
    c1 = (x0.long() + 1).clamp(0, wt - 1)
    r0 = y0.long().clamp(0, ht - 1)
    r1 = (y0.long() + 1).clamp(0, ht - 1)
    fx, fy = fx[..., None], fy[..., None]
    out = (1 - fy) * ((1 - fx) * tex[r0, c0] + fx * tex[r0, c1]) + fy * (
        (1 - fx) * tex[r1, c0] + fx * tex[r1, c1]
    )
    return torch.where(finite[..., None], out, torch.zeros_like(out))


def edge_topology(faces) -> list[list[int]]:
    """Reference of :func:`urhead.ops.antialias_topology` as nested lists."""
    f = faces.tolist()
    by_edge: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for i, t in enumerate(f):
        if len(set(t)) < 3:
            continue
        for k in range(3):
            a, b = t[(k + 1) % 3], t[(k + 2) % 3]
            by_edge.setdefault((min(a, b), max(a, b)), []).append((i, k))
    topo = [[-1, -1, -1] for _ in f]
    for slots in by_edge.values():
        if len(slots) == 2:
            (i, k), (j, m) = slots
            topo[i][k] = j
            topo[j][m] = i
    return topo


def antialias(color, raster, verts, faces, camera):
    """Reference of :func:`urhead.ops.antialias`, one pixel pair at a time. Decisions are
    made on detached float64 values; the blend weight is differentiable, with the kernel's
    1e-3 px guard applied to the gradient only (the forward uses the exact crossing)."""
    height, width, _ = color.shape
    cam = camera.world_to_camera(verts)
    k = camera.K.to(verts.dtype)
    proj = torch.stack(
        [k[0, 0] * cam[:, 0] / cam[:, 2] + k[0, 2], k[1, 1] * cam[:, 1] / cam[:, 2] + k[1, 2]], -1
    )
    f = faces.tolist()
    topo = edge_topology(faces)
    cam_d = cam.detach().double()

    def silhouette(t: int, e: int) -> bool:
        if topo[t][e] < 0:
            return True
        a, b, own = cam_d[f[t][(e + 1) % 3]], cam_d[f[t][(e + 2) % 3]], cam_d[f[t][e]]
        across = f[topo[t][e]]
        other = next((v for v in across if v not in f[t]), across[0])
        n = torch.linalg.cross(a, b)
        return not float(n @ own) * float(n @ cam_d[other]) < 0

    tri_id = raster.tri_id.tolist()
    depth = raster.depth.tolist()
    targets, weights, diffs = [], [], []
    for y in range(height):
        for x in range(width):
            for vertical in (False, True):
                x1, y1 = (x, y + 1) if vertical else (x + 1, y)
                if x1 >= width or y1 >= height:
                    continue
                t0, t1 = tri_id[y][x], tri_id[y1][x1]
                if t0 == t1:
                    continue
                if t0 < 0:
                    first = False
                elif t1 < 0:
                    first = True
                else:
                    d0, d1 = depth[y][x], depth[y1][x1]
                    first = d0 < d1 or (d0 == d1 and t0 < t1)
                t = t0 if first else t1
                cx, cy = (x, y) if first else (x1, y1)
                direction = 1.0 if first else -1.0
                found = None
                # Follow the segment through non-silhouette edges (the kernel's MAX_WALK).
                for _ in range(16):
                    if any(float(cam_d[v, 2]) <= camera.near for v in f[t]):
                        break
                    rel = proj[f[t]] - torch.tensor([cx + 0.5, cy + 0.5], dtype=proj.dtype)
                    if vertical:
                        rel = rel.flip(-1)
                    rd = rel.detach().double().tolist()
                    best = None
                    for e in range(3):
                        a, b = rd[(e + 1) % 3], rd[(e + 2) % 3]
                        if (a[1] < 0) == (b[1] < 0):
                            continue
                        crossing = direction * (a[0] * b[1] - b[0] * a[1]) / (b[1] - a[1])
                        if best is None or crossing > best[1]:
                            best = (e, crossing)
                    if best is None:
                        break
                    e, d = best
                    if silhouette(t, e):
                        found = (t, e, d, rel, rd)
                        break
                    far = t1 if first else t0
                    if topo[t][e] < 0 or topo[t][e] == far or d >= 1 + 1 / 16:
                        break
                    t = topo[t][e]
                if found is None:
                    continue
                t, e, d, rel, rd = found
                a, b = rd[(e + 1) % 3], rd[(e + 2) % 3]
                if not (abs(b[1] - a[1]) >= abs(b[0] - a[0]) and -1 / 16 < d < 1 + 1 / 16):
                    continue
                alpha_value = direction * (0.5 - min(max(d, 0.0), 1.0))
                if alpha_value == 0:
                    continue
                if abs(alpha_value) >= 0.5:
                    alpha = torch.tensor(alpha_value, dtype=color.dtype)
                else:
                    ra, rb = rel[(e + 1) % 3], rel[(e + 2) % 3]
                    num = ra[0] * rb[1] - rb[0] * ra[1]
                    den = rb[1] - ra[1]
                    guarded = num / (den + math.copysign(1e-3, float(den.detach())))
                    crossing_x = guarded + (num / den - guarded).detach()
                    alpha = direction * 0.5 - crossing_x
                target = (y, x) if alpha_value > 0 else (y1, x1)
                targets.append(target)
                weights.append(alpha)
                diffs.append(color[y1, x1] - color[y, x])
    if not targets:
        return color.clone()
    ty = torch.tensor([t[0] for t in targets])
    tx = torch.tensor([t[1] for t in targets])
    contrib = torch.stack(weights)[:, None].to(color.dtype) * torch.stack(diffs)
    return color.index_put((ty, tx), contrib, accumulate=True)


# --- Gaussian splatting --------------------------------------------------------------


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


# --- Masked image comparisons (urhead.ops.masked_ssim / masked_l1) --------------------------

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@lru_cache(maxsize=4)
def _gaussian_window(dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    w = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    return (w / w.sum()).to(dtype)


def _blur(x: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of (N, H, W) with zero padding (the 3DGS convention)."""
    w = _gaussian_window(x.dtype)
    x = x[:, None]
    x = F.conv2d(x, w.view(1, 1, -1, 1), padding=(SSIM_WINDOW // 2, 0))
    x = F.conv2d(x, w.view(1, 1, 1, -1), padding=(0, SSIM_WINDOW // 2))
    return x[:, 0]


def ssim_map(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (H, W) of (H, W, C) images (mean over channels), Gaussian window
    11 × 11, σ = 1.5, C1 = 0.01², C2 = 0.03² (Wang et al. 2004, as in 3DGS)."""
    x = image.permute(2, 0, 1)
    y = target.permute(2, 0, 1)
    mu_x, mu_y = _blur(x), _blur(y)
    var_x = _blur(x * x) - mu_x**2
    var_y = _blur(y * y) - mu_y**2
    cov = _blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (num / den).mean(0)


def masked_mean(values: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Σ m·v / max(Σ m, 1) over (H, W) or (H, W, C) values, the mask repeated over C; the
    plain mean without a mask."""
    if mask is None:
        return values.mean()
    weight = mask.to(values.dtype)
    if values.dim() == 3:
        weight = weight[..., None].expand_as(values)
    return (values * weight).sum() / weight.sum().clamp_min(1)


def masked_ssim(image, target, mask=None):
    """Reference of :func:`urhead.ops.masked_ssim`: plain-torch SSIM map, masked mean."""
    return masked_mean(ssim_map(image, target), mask)


def masked_l1(image, target, mask=None):
    """Reference of :func:`urhead.ops.masked_l1` (the image's first C channels)."""
    return masked_mean((image[..., : target.shape[-1]] - target).abs(), mask)


def masked_pixel_l1(values, pixels, target, mask):
    """Reference of :func:`urhead.ops.masked_pixel_l1`."""
    gt = target.reshape(-1, target.shape[-1]).index_select(0, pixels)
    weight = mask.reshape(-1).to(values.dtype).index_select(0, pixels) * (gt.abs().sum(-1) > 0)
    diff = (values - gt).abs().sum(-1)
    return (diff * weight).sum() / weight.sum().clamp_min(1)


def sh_shade(coeffs, dirs, degree):
    """Reference of :func:`urhead.ops.sh_shade`."""
    k = (degree + 1) ** 2
    sh = coeffs[:, : 3 * k].reshape(-1, k, 3)
    basis = sh_basis(dirs, degree)
    return ((basis[:, :, None] * sh).sum(1) + 0.5).clamp_min(0.0)


def sh_texture(tex, uv, dirs, degree, extra=None):
    """Reference of :func:`urhead.ops.sh_texture`: the lookup, then SH colour and the
    ``extra`` slice of the rows, as ``(rgb, extra)``."""
    rows = texture(tex, uv)
    extra = slice(0, 0) if extra is None else extra
    return sh_shade(rows, dirs.detach(), degree), rows[:, extra]


def composite(front, transmittance, back):
    """Reference of :func:`urhead.ops.composite`."""
    return front + transmittance[..., None] * back[..., :3]


def covered_pixels(tri_id):
    """Reference of :func:`urhead.ops.covered_pixels`."""
    return (tri_id.reshape(-1) >= 0).nonzero()[:, 0]


def scatter_pixels(values, pixels, background, size, fill=None):
    """Reference of :func:`urhead.ops.scatter_pixels`."""
    if fill is not None:
        values = torch.cat([values, fill.expand(values.shape[0], -1)], 1)
    flat = background.expand(size[0] * size[1], -1).index_put((pixels,), values)
    return flat.reshape(*size, -1)


def normalize_clamped(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) vectors over ``max(|v|, 1e-12)``: zero stays zero."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def rotate_normalize(rotations, vectors, transpose=False, rows=None):
    """Reference of :func:`urhead.ops.rotate_normalize` — the avatar's ``bmm`` before the
    kernel (``rows`` indexing the table first). Its ``|m|`` overflows where ``m²`` does
    (float32 beyond ~1.8e19, giving zero)."""
    if rows is not None:
        vectors = vectors[rows]
    matrices = rotations.transpose(1, 2) if transpose else rotations
    return normalize_clamped(torch.bmm(matrices, vectors[:, :, None])[..., 0])


def lift_gaussians_geometry(verts, rotations, face_verts, bary, normals, lift, centre):
    """Reference of :func:`urhead.ops.lift_gaussians_geometry` — the plain-torch lift the
    avatar used before the kernel: ``(means, normals, quats, frames, view_dirs)``. Its
    ``|m|`` overflows where ``m²`` does (float32 normals beyond ~1.8e19, giving a zero
    normal); the kernel's does not."""
    from urhead.ops.splat import normal_to_quat

    face_verts = face_verts.long()
    weights = bary[:, :, None]
    surface = (verts[face_verts] * weights).sum(1)
    frames = (rotations[face_verts] * weights[..., None]).sum(1)
    normal = normalize_clamped((frames * normals[:, None, :]).sum(-1))
    means = surface + lift[:, None] * normal
    rays = normalize_clamped(means.detach() - centre)
    view_dirs = normalize_clamped((rays[:, :, None] * frames.detach()).sum(1))
    return means, normal, normal_to_quat(normal), frames.detach(), view_dirs


def nearest_covered_pixel(covered):
    """Reference of :func:`urhead.ops.uv_error.nearest_covered_pixel` — the OpenCV call the
    sampling made before the kernel (needs at least one covered pixel)."""
    import cv2
    import numpy as np

    free = (~covered).numpy().astype(np.uint8)
    _, labels = cv2.distanceTransformWithLabels(
        free, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    # Labels number the zero (covered) pixels 1, 2, … in scan order.
    seeds = covered.reshape(-1).nonzero()[:, 0]
    return seeds[torch.from_numpy(labels.reshape(-1).astype(np.int64)) - 1]


def accumulate_uv_error(image, target, mask, pixels, uv, error, count):
    """Reference of :func:`urhead.ops.uv_error.accumulate_uv_error` — the torch and OpenCV
    code the sampling ran before the kernel: the samples (covered pixels, then missed ones
    charged to the nearest covered pixel's UV) binned with ``torch.bincount``."""
    h, w = mask.shape
    pixel_error = ((image.detach() - target).abs().sum(-1) * mask).reshape(-1)
    if pixels.numel() == 0:
        return
    covered = torch.zeros(h * w, dtype=torch.bool)
    covered[pixels] = True
    missed = ((mask.reshape(-1) > 0.5) & ~covered).nonzero()[:, 0]
    samples_uv, samples_error = uv, pixel_error[pixels]
    if missed.numel():
        nearest = nearest_covered_pixel(covered.reshape(h, w))[missed]
        slot = torch.empty(h * w, dtype=torch.int64)
        slot[pixels] = torch.arange(pixels.numel())
        samples_uv = torch.cat([uv, uv[slot[nearest]]])
        samples_error = torch.cat([samples_error, pixel_error[missed]])
    g = math.isqrt(error.numel())
    col = (samples_uv[:, 0] * g).long().clamp(0, g - 1)
    row = ((1 - samples_uv[:, 1]) * g).long().clamp(0, g - 1)
    cell = row * g + col
    error += torch.bincount(cell, samples_error.double(), minlength=g * g)
    count += torch.bincount(cell, minlength=g * g).double()
