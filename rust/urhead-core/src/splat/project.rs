//! EWA projection of 3D Gaussians (gsplat's classic perspective projection), forward and
//! adjoint side by side. One Gaussian at a time; [`project_one`] is the single source of
//! every cull decision, so the backward (which recomputes it) decides identically.

use rayon::prelude::*;

use super::{ProjectGradOutputs, ProjectGrads, ProjectInputs, ProjectNeeds, Projected, GAUSSIAN_CHUNK};
use super::{ALPHA_MIN, DILATION, EXTENT_CAP};
use crate::mat3::{map2, map3, map4, matmul, matmul_nt, matmul_tn, transpose, M3, V3};
use crate::parallel::optional_chunks;
use crate::sh::{sh_to_rgb, sh_to_rgb_backward};
use crate::{Camera, Real};

/// The camera in the kernel's float type, with the Jacobian clamp limits.
#[derive(Debug, Clone, Copy)]
pub(super) struct CameraT<T> {
    fx: T,
    fy: T,
    cx: T,
    cy: T,
    rot: M3<T>,
    trans: V3<T>,
    width: T,
    height: T,
    near: T,
    far: T,
    /// x/z is clamped to [−lim_x_neg, lim_x_pos] inside the Jacobian (same in y).
    lim_x_neg: T,
    lim_x_pos: T,
    lim_y_neg: T,
    lim_y_pos: T,
    /// Camera centre in world space, for SH view directions.
    centre: V3<T>,
}

impl<T: Real> CameraT<T> {
    pub(super) fn new(cam: &Camera) -> Self {
        let c = |x: f32| T::c(x as f64);
        let rot: M3<T> = map3(|r| map3(|k| c(cam.viewmat[r][k])));
        let trans: V3<T> = map3(|r| c(cam.viewmat[r][3]));
        let (fx, fy, cx, cy) = (c(cam.fx), c(cam.fy), c(cam.cx), c(cam.cy));
        let (w, h) = (T::c(cam.width as f64), T::c(cam.height as f64));
        let half = T::c(0.5);
        let margin = T::c(0.3);
        let (tan_x, tan_y) = (half * w / fx, half * h / fy);
        let rt_t = map3(|k| rot[0][k] * trans[0] + rot[1][k] * trans[1] + rot[2][k] * trans[2]);
        Self {
            fx,
            fy,
            cx,
            cy,
            rot,
            trans,
            width: w,
            height: h,
            near: c(cam.near),
            far: c(cam.far),
            lim_x_neg: cx / fx + margin * tan_x,
            lim_x_pos: (w - cx) / fx + margin * tan_x,
            lim_y_neg: cy / fy + margin * tan_y,
            lim_y_pos: (h - cy) / fy + margin * tan_y,
            centre: rt_t.map(|v| -v),
        }
    }
}

/// Everything the forward computes for one visible Gaussian (the backward recomputes it).
#[derive(Debug, Clone, Copy)]
pub(super) struct ProjectedOne<T> {
    pub p_cam: V3<T>,
    pub quat_norm: T,
    pub q: [T; 4],
    pub rot: M3<T>,
    pub scale: V3<T>,
    pub cov_cam: M3<T>,
    /// Rows of the 2×3 Jacobian, the last column after the clamp.
    pub jac: [V3<T>; 2],
    /// Whether x/z (resp. y/z) was clamped.
    pub clamped: [bool; 2],
    pub conic: [T; 3],
    pub mean2d: [T; 2],
    pub radius: [i32; 2],
}

#[inline(always)]
pub(super) fn quat_to_rotmat<T: Real>(q: [T; 4]) -> M3<T> {
    let [w, x, y, z] = q;
    let (one, two) = (T::one(), T::c(2.0));
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// ∂L/∂q for R = quat_to_rotmat(q), given G = ∂L/∂R.
#[inline]
fn quat_to_rotmat_backward<T: Real>(q: [T; 4], g: &M3<T>) -> [T; 4] {
    let [w, x, y, z] = q;
    let two = T::c(2.0);
    [
        two * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]),
        two * (y * g[0][1] + z * g[0][2] + y * g[1][0] - two * x * g[1][1] - w * g[1][2]
            + z * g[2][0]
            + w * g[2][1]
            - two * x * g[2][2]),
        two * (-two * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2] - w * g[2][0]
            + z * g[2][1]
            - two * y * g[2][2]),
        two * (-two * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - two * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]),
    ]
}

/// The cut-off in standard deviations where alpha reaches 1/255: min(3.33, √(2 ln(255·o))).
#[inline]
pub(super) fn extent_sigmas<T: Real>(opacity: T) -> T {
    let e = (T::c(2.0) * (opacity / T::c(ALPHA_MIN)).ln()).sqrt();
    let cap = T::c(EXTENT_CAP);
    if e < cap {
        e
    } else {
        cap
    }
}

#[inline]
fn to_radius<T: Real>(x: T) -> i32 {
    // Saturating: a Gaussian wider than 2^30 px covers every tile anyway.
    let x = x.ceil().to_f64().unwrap_or(0.0);
    if x >= (1 << 30) as f64 {
        1 << 30
    } else if x >= 0.0 {
        x as i32
    } else {
        0
    }
}

/// Projects one Gaussian; `None` when it is culled (behind the near plane or beyond far,
/// zero quaternion, zero/subnormal scale, opacity < 1/255, non-positive or non-finite
/// 2D determinant, zero radius, or entirely off-screen). Predicates are written so that
/// NaN culls.
#[inline(always)]
pub(super) fn project_one<T: Real>(
    cam: &CameraT<T>,
    mean: V3<T>,
    quat: [T; 4],
    scale: V3<T>,
    opacity: T,
) -> Option<ProjectedOne<T>> {
    let r = &cam.rot;
    let p_cam: V3<T> = map3(|i| r[i][0] * mean[0] + r[i][1] * mean[1] + r[i][2] * mean[2] + cam.trans[i]);
    let [x, y, z] = p_cam;
    if !(z >= cam.near && z <= cam.far) {
        return None;
    }
    let n2 = quat.iter().fold(T::zero(), |s, &v| s + v * v);
    if !(n2 > T::zero() && n2.is_finite()) {
        return None;
    }
    if scale
        .iter()
        .any(|s| !(s.abs() >= T::min_positive_value() && s.is_finite()))
    {
        return None;
    }
    if !(opacity >= T::c(ALPHA_MIN)) {
        return None;
    }
    let quat_norm = n2.sqrt();
    let q = map4(|k| quat[k] / quat_norm);
    let rot = quat_to_rotmat(q);
    let m: M3<T> = map3(|i| map3(|j| rot[i][j] * scale[j]));
    let cov_world = matmul_nt(&m, &m);
    let cov_cam = matmul(&matmul(r, &cov_world), &transpose(r));

    let (ux, uy) = (x / z, y / z);
    let (tx, cxl) = clamp_ratio(ux, cam.lim_x_neg, cam.lim_x_pos);
    let (ty, cyl) = clamp_ratio(uy, cam.lim_y_neg, cam.lim_y_pos);
    let zero = T::zero();
    let jac = [
        [cam.fx / z, zero, -cam.fx * tx / z],
        [zero, cam.fy / z, -cam.fy * ty / z],
    ];
    let cov2 = jac_cov_jt(&jac, &cov_cam);
    let dil = T::c(DILATION);
    let cov2d = [cov2[0] + dil, cov2[1], cov2[2] + dil];
    let det = cov2d[0] * cov2d[2] - cov2d[1] * cov2d[1];
    if !(det > zero && det.is_finite()) {
        return None;
    }
    let conic = [cov2d[2] / det, -cov2d[1] / det, cov2d[0] / det];
    if conic.iter().any(|c| !c.is_finite()) {
        return None;
    }
    let mean2d = [cam.fx * ux + cam.cx, cam.fy * uy + cam.cy];
    let ext = extent_sigmas(opacity);
    let radius = [to_radius(ext * cov2d[0].sqrt()), to_radius(ext * cov2d[2].sqrt())];
    if radius[0] <= 0 || radius[1] <= 0 {
        return None;
    }
    let (rx, ry) = (T::c(radius[0] as f64), T::c(radius[1] as f64));
    if !(mean2d[0] + rx > zero
        && mean2d[0] - rx < cam.width
        && mean2d[1] + ry > zero
        && mean2d[1] - ry < cam.height)
    {
        return None;
    }
    Some(ProjectedOne {
        p_cam,
        quat_norm,
        q,
        rot,
        scale,
        cov_cam,
        jac,
        clamped: [cxl, cyl],
        conic,
        mean2d,
        radius,
    })
}

/// x/z limited to [−neg, pos]; returns the value and whether it was clamped.
#[inline]
fn clamp_ratio<T: Real>(u: T, neg: T, pos: T) -> (T, bool) {
    if u < -neg {
        (-neg, true)
    } else if u > pos {
        (pos, true)
    } else {
        (u, false)
    }
}

/// J·Σ·Jᵀ for a 2×3 J and symmetric Σ, as (a, b, c).
#[inline]
fn jac_cov_jt<T: Real>(j: &[V3<T>; 2], s: &M3<T>) -> [T; 3] {
    let js: [V3<T>; 2] = map2(|r| map3(|k| j[r][0] * s[0][k] + j[r][1] * s[1][k] + j[r][2] * s[2][k]));
    let dot = |a: &V3<T>, b: &V3<T>| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    [dot(&js[0], &j[0]), dot(&js[0], &j[1]), dot(&js[1], &j[1])]
}

/// Unit view direction from the camera centre to `mean`, and the distance.
#[inline]
pub(super) fn view_dir<T: Real>(cam: &CameraT<T>, mean: V3<T>) -> (V3<T>, T) {
    let d: V3<T> = map3(|i| mean[i] - cam.centre[i]);
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    (map3(|k| d[k] / len), len)
}

pub fn project_forward<T: Real>(camera: &Camera, inputs: &ProjectInputs<T>) -> crate::Result<Projected<T>> {
    inputs.validate()?;
    let cam = CameraT::<T>::new(camera);
    let n = inputs.num_gaussians;
    let mut means2d = vec![T::zero(); n * 2];
    let mut conics = vec![T::zero(); n * 3];
    let mut depths = vec![T::zero(); n];
    let mut radii = vec![0i32; n * 2];
    let mut colors = inputs.sh.map(|_| vec![T::zero(); n * 3]);
    let mut color_chunks = optional_chunks(
        colors.as_deref_mut(),
        GAUSSIAN_CHUNK * 3,
        n.div_ceil(GAUSSIAN_CHUNK),
    );
    means2d
        .par_chunks_mut(GAUSSIAN_CHUNK * 2)
        .zip(conics.par_chunks_mut(GAUSSIAN_CHUNK * 3))
        .zip(depths.par_chunks_mut(GAUSSIAN_CHUNK))
        .zip(radii.par_chunks_mut(GAUSSIAN_CHUNK * 2))
        .zip(color_chunks.par_iter_mut())
        .enumerate()
        .for_each(|(chunk, ((((m2, co), de), ra), col))| {
            for (k, depth) in de.iter_mut().enumerate() {
                let i = chunk * GAUSSIAN_CHUNK + k;
                let Some(p) = project_one(
                    &cam,
                    inputs.mean(i),
                    inputs.quat(i),
                    inputs.scale(i),
                    inputs.opacities[i],
                ) else {
                    continue;
                };
                m2[k * 2..k * 2 + 2].copy_from_slice(&p.mean2d);
                co[k * 3..k * 3 + 3].copy_from_slice(&p.conic);
                *depth = p.p_cam[2];
                ra[k * 2..k * 2 + 2].copy_from_slice(&p.radius);
                if let (Some(sh), Some(col)) = (inputs.sh, col.as_deref_mut()) {
                    let (dir, _) = view_dir(&cam, inputs.mean(i));
                    col[k * 3..k * 3 + 3].copy_from_slice(&sh_to_rgb(sh.degree, dir, sh.of(i)));
                }
            }
        });
    Ok(Projected {
        means2d,
        conics,
        depths,
        radii,
        colors,
    })
}

/// Adjoint of [`project_forward`]: recomputes each Gaussian's projection (same decisions)
/// and maps ∂L/∂(means2d, conics, colors) to the inputs asked for in `needs`. Depths and
/// radii carry no gradient (sorting and culling are discrete).
pub fn project_backward<T: Real>(
    camera: &Camera,
    inputs: &ProjectInputs<T>,
    grads: &ProjectGradOutputs<T>,
    needs: &ProjectNeeds,
) -> crate::Result<ProjectGrads<T>> {
    inputs.validate()?;
    grads.validate(inputs)?;
    let cam = CameraT::<T>::new(camera);
    let n = inputs.num_gaussians;
    let k_sh = inputs.sh.map_or(0, |s| s.num_coeffs);
    let mut v_means = vec![T::zero(); n * 3];
    let mut v_quats = vec![T::zero(); n * 4];
    let mut v_scales = vec![T::zero(); n * 3];
    let mut v_sh = vec![T::zero(); n * k_sh * 3];
    let mut sh_chunks: Vec<&mut [T]> = if k_sh > 0 {
        v_sh.chunks_mut(GAUSSIAN_CHUNK * k_sh * 3).collect()
    } else {
        (0..n.div_ceil(GAUSSIAN_CHUNK))
            .map(|_| Default::default())
            .collect()
    };
    v_means
        .par_chunks_mut(GAUSSIAN_CHUNK * 3)
        .zip(v_quats.par_chunks_mut(GAUSSIAN_CHUNK * 4))
        .zip(v_scales.par_chunks_mut(GAUSSIAN_CHUNK * 3))
        .zip(sh_chunks.par_iter_mut())
        .enumerate()
        .for_each(|(chunk, (((vm, vq), vs), vsh))| {
            for k in 0..vm.len() / 3 {
                let i = chunk * GAUSSIAN_CHUNK + k;
                let Some(p) = project_one(
                    &cam,
                    inputs.mean(i),
                    inputs.quat(i),
                    inputs.scale(i),
                    inputs.opacities[i],
                ) else {
                    continue;
                };
                let v_mean2d = grads
                    .v_means2d
                    .map_or([T::zero(); 2], |g| [g[i * 2], g[i * 2 + 1]]);
                let v_conic = grads
                    .v_conics
                    .map_or([T::zero(); 3], |g| [g[i * 3], g[i * 3 + 1], g[i * 3 + 2]]);
                let (v_pc, v_q, v_s) = project_one_backward(&cam, &p, v_mean2d, v_conic);
                let r = &cam.rot;
                let mut v_mean: V3<T> = map3(|j| r[0][j] * v_pc[0] + r[1][j] * v_pc[1] + r[2][j] * v_pc[2]);
                if let (Some(sh), Some(g)) = (inputs.sh, grads.v_colors) {
                    let (dir, len) = view_dir(&cam, inputs.mean(i));
                    let v_rgb = [g[i * 3], g[i * 3 + 1], g[i * 3 + 2]];
                    let v_sh_i = if needs.sh {
                        Some(&mut vsh[k * k_sh * 3..(k + 1) * k_sh * 3])
                    } else {
                        None
                    };
                    let v_dir = sh_to_rgb_backward(sh.degree, dir, sh.of(i), v_rgb, v_sh_i);
                    // d/dm (d/|d|) = (I − dir·dirᵀ)/|d|
                    let proj = v_dir[0] * dir[0] + v_dir[1] * dir[1] + v_dir[2] * dir[2];
                    for a in 0..3 {
                        v_mean[a] += (v_dir[a] - dir[a] * proj) / len;
                    }
                }
                vm[k * 3..k * 3 + 3].copy_from_slice(&v_mean);
                vq[k * 4..k * 4 + 4].copy_from_slice(&v_q);
                vs[k * 3..k * 3 + 3].copy_from_slice(&v_s);
            }
        });
    Ok(ProjectGrads {
        v_means: needs.means.then_some(v_means),
        v_quats: needs.quats.then_some(v_quats),
        v_scales: needs.scales.then_some(v_scales),
        v_sh: (needs.sh && k_sh > 0).then_some(v_sh),
    })
}

/// Adjoint of [`project_one`] for the 2D mean and conic: returns ∂L/∂p_cam, ∂L/∂quat
/// (through the normalisation) and ∂L/∂scale.
#[inline]
fn project_one_backward<T: Real>(
    cam: &CameraT<T>,
    p: &ProjectedOne<T>,
    v_mean2d: [T; 2],
    v_conic: [T; 3],
) -> (V3<T>, [T; 4], V3<T>) {
    let zero = T::zero();
    let two = T::c(2.0);
    let [x, y, z] = p.p_cam;
    // conic = inverse(cov2d): ∂L/∂cov = −conic·Gc·conic, Gc symmetric with halved off-diagonal.
    let [ca, cb, cc] = p.conic;
    let half = T::c(0.5);
    let gc = [[v_conic[0], half * v_conic[1]], [half * v_conic[1], v_conic[2]]];
    let con = [[ca, cb], [cb, cc]];
    let mut g_cov = [[zero; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            let mut s = zero;
            for k in 0..2 {
                for l in 0..2 {
                    s += con[i][k] * gc[k][l] * con[l][j];
                }
            }
            g_cov[i][j] = -s;
        }
    }
    // cov2d = J·Σc·Jᵀ (+ dilation): ∂L/∂Σc = Jᵀ·G·J, ∂L/∂J = 2·G·J·Σc.
    let j = &p.jac;
    let gj: [V3<T>; 2] = map2(|r| map3(|k| g_cov[r][0] * j[0][k] + g_cov[r][1] * j[1][k]));
    let g_sigma_cam: M3<T> = map3(|a| map3(|b| j[0][a] * gj[0][b] + j[1][a] * gj[1][b]));
    let v_jac: [V3<T>; 2] = map2(|r| {
        map3(|k| two * (gj[r][0] * p.cov_cam[0][k] + gj[r][1] * p.cov_cam[1][k] + gj[r][2] * p.cov_cam[2][k]))
    });
    // Σc = W·Σ·Wᵀ, Σ = M·Mᵀ, M = R·diag(s).
    let w = &cam.rot;
    let g_sigma = matmul(&matmul_tn(w, &g_sigma_cam), w);
    let m: M3<T> = map3(|a| map3(|b| p.rot[a][b] * p.scale[b]));
    let g_m: M3<T> = map3(|a| {
        map3(|b| two * (g_sigma[a][0] * m[0][b] + g_sigma[a][1] * m[1][b] + g_sigma[a][2] * m[2][b]))
    });
    let g_rot: M3<T> = map3(|a| map3(|b| g_m[a][b] * p.scale[b]));
    let v_scale: V3<T> =
        map3(|b| p.rot[0][b] * g_m[0][b] + p.rot[1][b] * g_m[1][b] + p.rot[2][b] * g_m[2][b]);
    let v_qn = quat_to_rotmat_backward(p.q, &g_rot);
    let dotq = (0..4).fold(zero, |s, k| s + p.q[k] * v_qn[k]);
    let v_quat = map4(|k| (v_qn[k] - p.q[k] * dotq) / p.quat_norm);

    // mean2d = (fx·x/z + cx, fy·y/z + cy)
    let rz = T::one() / z;
    let rz2 = rz * rz;
    let mut v_pc = [
        cam.fx * rz * v_mean2d[0],
        cam.fy * rz * v_mean2d[1],
        -(cam.fx * x * v_mean2d[0] + cam.fy * y * v_mean2d[1]) * rz2,
    ];
    // J = [[fx/z, 0, −fx·tx/z], [0, fy/z, −fy·ty/z]] with tx = x/z unless clamped.
    v_pc[2] -= (cam.fx * v_jac[0][0] + cam.fy * v_jac[1][1]) * rz2;
    for (axis, f, coord) in [(0usize, cam.fx, x), (1, cam.fy, y)] {
        let g = v_jac[axis][2];
        if p.clamped[axis] {
            // J = −f·L/z with L constant: no gradient to x (resp. y).
            let lim_over_z = -p.jac[axis][2] / f; // = L / z
            v_pc[2] += f * lim_over_z * rz * g;
        } else {
            v_pc[axis] -= f * rz2 * g;
            v_pc[2] += two * f * coord * rz2 * rz * g;
        }
    }
    (v_pc, v_quat, v_scale)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{record_stability, Rng};

    fn camera() -> Camera {
        let view = [
            [1.0, 0.0, 0.0, 0.05],
            [0.0, 1.0, 0.0, -0.02],
            [0.0, 0.0, 1.0, 0.1],
            [0.0, 0.0, 0.0, 1.0],
        ];
        Camera::new(
            [[300.0, 0.0, 70.0], [0.0, 280.0, 40.0], [0.0, 0.0, 1.0]],
            view,
            128,
            96,
            0.01,
            100.0,
        )
        .unwrap()
    }

    /// Scalar loss of the projection of one Gaussian: a fixed linear functional of the
    /// 2D mean and conic.
    fn loss(cam: &CameraT<f64>, mean: V3<f64>, quat: [f64; 4], scale: V3<f64>, w: &[f64; 5]) -> f64 {
        let p = project_one(cam, mean, quat, scale, 0.8).unwrap();
        w[0] * p.mean2d[0] + w[1] * p.mean2d[1] + w[2] * p.conic[0] + w[3] * p.conic[1] + w[4] * p.conic[2]
    }

    /// Returns the worst |fd − analytic| / (1 + |fd|) over mean, scale and quat.
    fn check_fd(mean: V3<f64>, expect_clamped: [bool; 2]) -> f64 {
        let cam = CameraT::<f64>::new(&camera());
        let mut rng = Rng::new(17);
        let quat = [0.8, -0.3, 0.4, 0.2];
        let scale = [0.05, 0.01, 0.03];
        let w: [f64; 5] = std::array::from_fn(|_| rng.uniform(-1.0, 1.0));
        let p = project_one(&cam, mean, quat, scale, 0.8).unwrap();
        assert_eq!(p.clamped, expect_clamped);
        let (v_pc, v_q, v_s) = project_one_backward(&cam, &p, [w[0], w[1]], [w[2], w[3], w[4]]);
        let v_mean: V3<f64> = map3(|j| (0..3).map(|i| cam.rot[i][j] * v_pc[i]).sum());
        let h = 1e-6;
        let mut worst = 0.0f64;
        for a in 0..3 {
            let (mut mp, mut mm) = (mean, mean);
            mp[a] += h;
            mm[a] -= h;
            let fd = (loss(&cam, mp, quat, scale, &w) - loss(&cam, mm, quat, scale, &w)) / (2.0 * h);
            worst = worst.max((fd - v_mean[a]).abs() / (1.0 + fd.abs()));
            assert!(
                (fd - v_mean[a]).abs() <= 1e-5 * (1.0 + fd.abs()),
                "mean[{a}]: {fd} vs {}",
                v_mean[a]
            );
            let (mut sp, mut sm) = (scale, scale);
            sp[a] += h;
            sm[a] -= h;
            let fd = (loss(&cam, mean, quat, sp, &w) - loss(&cam, mean, quat, sm, &w)) / (2.0 * h);
            worst = worst.max((fd - v_s[a]).abs() / (1.0 + fd.abs()));
            assert!(
                (fd - v_s[a]).abs() <= 1e-5 * (1.0 + fd.abs()),
                "scale[{a}]: {fd} vs {}",
                v_s[a]
            );
        }
        for a in 0..4 {
            let (mut qp, mut qm) = (quat, quat);
            qp[a] += h;
            qm[a] -= h;
            let fd = (loss(&cam, mean, qp, scale, &w) - loss(&cam, mean, qm, scale, &w)) / (2.0 * h);
            worst = worst.max((fd - v_q[a]).abs() / (1.0 + fd.abs()));
            assert!(
                (fd - v_q[a]).abs() <= 1e-5 * (1.0 + fd.abs()),
                "quat[{a}]: {fd} vs {}",
                v_q[a]
            );
        }
        worst
    }

    #[test]
    fn projection_gradient_matches_fd_on_screen() {
        check_fd([0.03, 0.01, 0.6], [false, false]);
    }

    /// NUMERICS.md case 10: off-screen means with an off-centre principal point — FD on
    /// the clamped branch too.
    #[test]
    fn case10_projection_gradient_matches_fd_clamped_branches() {
        let worst = [
            check_fd([-0.3, 0.01, 0.6], [true, false]),
            check_fd([0.03, 0.22, 0.6], [false, true]),
            check_fd([0.2, -0.14, 0.6], [true, true]),
        ]
        .into_iter()
        .fold(0.0, f64::max);
        record_stability(
            10,
            "Rust projection, clamped x, y and both: gradient vs central differences, |an − fd| / (1 + |fd|)",
            "splat::project::tests::case10_projection_gradient_matches_fd_clamped_branches",
            worst,
            1e-5,
        );
    }
}
