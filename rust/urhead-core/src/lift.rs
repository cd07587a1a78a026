//! The Gaussian lift: each Gaussian's geometry from its point on the posed surface, forward
//! and adjoint side by side (DESIGN.md step 4). A Gaussian sits in face `f` at barycentrics
//! `b`, with a rest-frame normal `N` and a lift `D (+ E)` read from the UV maps:
//!
//! - `frame = Σ_k b_k·R_{f_k}`: the skinning rotations of the face's vertices, blended;
//! - `n̂ = m / max(|m|, 1e-12)` with `m = frame·N` (zero stays zero);
//! - `mean = Σ_k b_k·v_{f_k} + lift·n̂`;
//! - `quat = normal_to_quat(n̂)` (Duff et al.'s branchless basis, below);
//! - `view_dir = normalise(frameᵀ·normalise(mean − centre))`: the unit direction from the
//!   camera in the surface's rest frame, what SH colour is evaluated along (a constant).
//!
//! Gradients flow to the vertices, the skinning rotations (through the posed normal as well
//! as the position), the rest normals and the lifts, from the gradients of `mean`, `n̂` and
//! `quat`; `frame` and `view_dir` are constants.
//!
//! Non-finite normals and lifts are data, not errors (a map texel may hold anything): a
//! NaN normal gives a NaN mean (the splatter culls it) and the identity quaternion. A
//! Gaussian whose upstream gradient is zero — culled, occluded — contributes exactly zero,
//! and a quaternion at its fallback passes exactly zero, never `0·NaN`.

use rayon::prelude::*;

use crate::error::{check_finite, check_indices, check_len, checked_size, Error, Result};
use crate::mat3::{dot, map3, matvec, matvec_t, M3, V3};
use crate::memory::zeroed;
use crate::rotate::{normalise, normalise_backward};
use crate::Real;

/// Gaussians per rayon task; fixed, so the partition does not depend on the thread count
/// (each Gaussian is independent anyway).
const CHUNK: usize = 1024;
/// Vertices per rayon task of the gradient gather.
const VERTEX_CHUNK: usize = 256;

/// The arguments shared by the forward and the backward (row-major, contiguous).
#[derive(Clone, Copy)]
pub struct LiftInputs<'a, T> {
    /// (V, 3) posed vertices.
    pub verts: &'a [T],
    /// (V, 3, 3) per-vertex skinning rotations (rest frame → world).
    pub rotations: &'a [T],
    /// (N, 3) the vertex ids of each Gaussian's face.
    pub face_verts: &'a [i32],
    /// (N, 3) barycentrics in that face (constants).
    pub bary: &'a [T],
    /// (N, 3) rest-frame normals, any length (zero and non-finite allowed).
    pub normals: &'a [T],
    /// (N,) distance along the posed normal.
    pub lift: &'a [T],
    /// (3,) camera centre, world space (a constant).
    pub centre: &'a [T],
}

/// The forward's outputs.
#[derive(Debug, Clone)]
pub struct Lifted<T> {
    /// (N, 3) world positions.
    pub means: Vec<T>,
    /// (N, 3) posed unit normals n̂ (zero for a zero normal).
    pub normals: Vec<T>,
    /// (N, 4) rotations (w, x, y, z) whose local z axis is n̂.
    pub quats: Vec<T>,
    /// (N, 3, 3) blended skinning rotations.
    pub frames: Vec<T>,
    /// (N, 3) unit view directions in the rest frame.
    pub view_dirs: Vec<T>,
}

/// Upstream gradients; `None` is zero.
#[derive(Clone, Copy, Default)]
pub struct LiftGradOutputs<'a, T> {
    /// (N, 3)
    pub v_means: Option<&'a [T]>,
    /// (N, 3)
    pub v_normals: Option<&'a [T]>,
    /// (N, 4)
    pub v_quats: Option<&'a [T]>,
}

/// Which input gradients to compute.
#[derive(Debug, Clone, Copy, Default)]
pub struct LiftNeeds {
    pub verts: bool,
    pub rotations: bool,
    pub normals: bool,
    pub lift: bool,
}

/// Gradients of [`lift_backward`]; a field is `Some` exactly when it was asked for.
#[derive(Debug, Clone, Default)]
pub struct LiftGrads<T> {
    /// (V, 3)
    pub v_verts: Option<Vec<T>>,
    /// (V, 3, 3)
    pub v_rotations: Option<Vec<T>>,
    /// (N, 3)
    pub v_normals: Option<Vec<T>>,
    /// (N,)
    pub v_lift: Option<Vec<T>>,
}

impl<T: Real> LiftInputs<'_, T> {
    /// Checks every argument; returns `(N, V)`.
    fn validate(&self) -> Result<(usize, usize)> {
        let n = self.face_verts.len() / 3;
        check_len("face_verts", self.face_verts, n * 3, "(N, 3)")?;
        let v = self.verts.len() / 3;
        check_len("verts", self.verts, v * 3, "(V, 3)")?;
        check_len(
            "rotations",
            self.rotations,
            v * 9,
            &format!("(V, 3, 3) with V = {v} like verts"),
        )?;
        let per_gaussian = |arg, data: &[T], width: usize, layout: &str| {
            check_len(
                arg,
                data,
                n * width,
                &format!("{layout} with N = {n} like face_verts"),
            )
        };
        per_gaussian("bary", self.bary, 3, "(N, 3)")?;
        per_gaussian("normals", self.normals, 3, "(N, 3)")?;
        per_gaussian("lift", self.lift, 1, "(N,)")?;
        check_len("centre", self.centre, 3, "(3,)")?;
        if n > 0 && v == 0 {
            return Err(Error::Shape {
                arg: "verts",
                expected: "(V, 3) with at least one vertex".into(),
                got: "0 vertices".into(),
            });
        }
        // Corner ids `3·g + k` of the gradient gather are u32.
        checked_size("Gaussian corners", &[n, 3], u32::MAX as usize)?;
        check_indices("face_verts", self.face_verts, 0, v as i64)?;
        check_finite("verts", self.verts)?;
        check_finite("rotations", self.rotations)?;
        check_finite("bary", self.bary)?;
        check_finite("centre", self.centre)?;
        Ok((n, v))
    }

    #[inline(always)]
    fn corners(&self, i: usize) -> [usize; 3] {
        map3(|k| self.face_verts[3 * i + k] as usize)
    }

    #[inline(always)]
    fn weights(&self, i: usize) -> V3<T> {
        [self.bary[3 * i], self.bary[3 * i + 1], self.bary[3 * i + 2]]
    }

    /// Σ_k b_k·R_{f_k}.
    #[inline(always)]
    fn frame(&self, i: usize) -> M3<T> {
        let (f, b) = (self.corners(i), self.weights(i));
        let r = |k: usize, e: usize| self.rotations[9 * f[k] + e];
        let mut m = [[T::zero(); 3]; 3];
        for (e, slot) in m.iter_mut().flatten().enumerate() {
            *slot = b[0] * r(0, e) + b[1] * r(1, e) + b[2] * r(2, e);
        }
        m
    }

    /// Σ_k b_k·v_{f_k}.
    #[inline(always)]
    fn surface(&self, i: usize) -> V3<T> {
        let (f, b) = (self.corners(i), self.weights(i));
        let v = |k: usize, c: usize| self.verts[3 * f[k] + c];
        map3(|c| b[0] * v(0, c) + b[1] * v(1, c) + b[2] * v(2, c))
    }

    #[inline(always)]
    fn rest_normal(&self, i: usize) -> V3<T> {
        [
            self.normals[3 * i],
            self.normals[3 * i + 1],
            self.normals[3 * i + 2],
        ]
    }

    /// The posed normal of Gaussian `i`, recomputed identically by both passes.
    #[inline(always)]
    fn posed(&self, i: usize) -> Posed<T> {
        let frame = self.frame(i);
        let rest = self.rest_normal(i);
        let (normal, length) = normalise(matvec(&frame, &rest));
        Posed {
            frame,
            normal,
            length,
            quat: Quat::of(normal),
        }
    }
}

/// One Gaussian's posed normal and what its adjoint needs.
struct Posed<T> {
    frame: M3<T>,
    /// n̂ = frame·rest / length.
    normal: V3<T>,
    /// |frame·rest| (may be below the floor).
    length: T,
    quat: Quat<T>,
}

/// `normal_to_quat` of one normal (python/urhead/ops/splat.py), with its adjoint's state.
/// The normal is scaled by its largest component and normalised to `u`; for `u_z ≥ 0` the
/// shortest arc from +z, `q = (1 + u_z, −u_y, u_x, 0)/√(2(1 + u_z))`; for `u_z < 0` the arc
/// from −z after a half-turn about x, `q = (−u_y, 1 − u_z, 0, u_x)/√(2(1 − u_z))`. Both
/// denominators are ≥ √2. Zero or non-finite normals give the identity, zero gradient.
#[derive(Debug, Clone, Copy)]
pub struct Quat<T> {
    pub q: [T; 4],
    /// The unit normal, and the divisors that made it: `u = (n / peak) / len`.
    u: V3<T>,
    peak: T,
    len: T,
    /// √(2(1 ± u_z)).
    s: T,
    /// `None` at the fallback.
    up: Option<bool>,
}

impl<T: Real> Quat<T> {
    #[inline(always)]
    pub fn of(n: V3<T>) -> Self {
        let (zero, one) = (T::zero(), T::one());
        let fallback = Self {
            q: [one, zero, zero, zero],
            u: [zero, zero, one],
            peak: one,
            len: one,
            s: one,
            up: None,
        };
        if !n.iter().all(|x| x.is_finite()) {
            return fallback;
        }
        let peak = n[0].abs().max(n[1].abs()).max(n[2].abs());
        if peak == zero {
            // finite and non-negative here
            return fallback;
        }
        let scaled = n.map(|x| x / peak);
        let len = dot(&scaled, &scaled).sqrt();
        let u = scaled.map(|x| x / len);
        let two = T::c(2.0);
        let up = u[2] >= zero;
        let (s, q) = if up {
            let s = (two * (one + u[2])).sqrt();
            (s, [(one + u[2]) / s, -u[1] / s, u[0] / s, zero / s])
        } else {
            let s = (two * (one - u[2])).sqrt();
            (s, [-u[1] / s, (one - u[2]) / s, zero / s, u[0] / s])
        };
        Self {
            q,
            u,
            peak,
            len,
            s,
            up: Some(up),
        }
    }

    /// ∂L/∂n from ∂L/∂q. The scale by `peak` cancels in `u`, so its gradient is exactly
    /// zero and only the normalisation's projection remains.
    #[inline(always)]
    pub fn backward(&self, v_q: &[T; 4]) -> V3<T> {
        let Some(up) = self.up else {
            return [T::zero(); 3];
        };
        let s = self.s;
        let along =
            (v_q[0] * self.q[0] + v_q[1] * self.q[1] + v_q[2] * self.q[2] + v_q[3] * self.q[3]) / (s * s);
        let v_u = if up {
            [v_q[2] / s, -v_q[1] / s, v_q[0] / s - along]
        } else {
            [v_q[3] / s, -v_q[0] / s, -v_q[1] / s + along]
        };
        let proj = dot(&self.u, &v_u);
        map3(|c| (v_u[c] - self.u[c] * proj) / self.len / self.peak)
    }
}

/// Lifts every Gaussian: means, posed normals, quaternions, frames and view directions.
pub fn lift_forward<T: Real>(inputs: &LiftInputs<'_, T>) -> Result<Lifted<T>> {
    let (n, _) = inputs.validate()?;
    let centre = [inputs.centre[0], inputs.centre[1], inputs.centre[2]];
    let mut means = zeroed("lifted means", n * 3)?;
    let mut normals = zeroed("lifted normals", n * 3)?;
    let mut quats = zeroed("lifted quaternions", n * 4)?;
    let mut frames = zeroed("lifted frames", n * 9)?;
    let mut view_dirs = zeroed("lifted view directions", n * 3)?;
    (
        means.par_chunks_mut(CHUNK * 3),
        normals.par_chunks_mut(CHUNK * 3),
        quats.par_chunks_mut(CHUNK * 4),
        frames.par_chunks_mut(CHUNK * 9),
        view_dirs.par_chunks_mut(CHUNK * 3),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(c, (means, normals, quats, frames, view_dirs))| {
            for j in 0..means.len() / 3 {
                let i = c * CHUNK + j;
                let p = inputs.posed(i);
                let surface = inputs.surface(i);
                let lift = inputs.lift[i];
                let mean = map3(|k| surface[k] + lift * p.normal[k]);
                let (ray, _) = normalise(map3(|k| mean[k] - centre[k]));
                let (local, _) = normalise(matvec_t(&p.frame, &ray));
                means[3 * j..3 * j + 3].copy_from_slice(&mean);
                normals[3 * j..3 * j + 3].copy_from_slice(&p.normal);
                quats[4 * j..4 * j + 4].copy_from_slice(&p.quat.q);
                for (dst, src) in frames[9 * j..9 * j + 9].iter_mut().zip(p.frame.iter().flatten()) {
                    *dst = *src;
                }
                view_dirs[3 * j..3 * j + 3].copy_from_slice(&local);
            }
        });
    Ok(Lifted {
        means,
        normals,
        quats,
        frames,
        view_dirs,
    })
}

#[inline(always)]
fn row<T: Real, const W: usize>(data: Option<&[T]>, i: usize) -> [T; W] {
    match data {
        Some(d) => std::array::from_fn(|k| d[W * i + k]),
        None => [T::zero(); W],
    }
}

/// The adjoint of [`lift_forward`], computing only the gradients flagged in `needs`.
///
/// Per-Gaussian gradients are written in parallel over fixed chunks. The vertex and
/// rotation gradients sum contributions of many Gaussians into shared vertices; they are
/// *gathered*, not scattered: a counting sort lists each vertex's Gaussian corners in
/// ascending order (O(N + V), built per call since the Gaussians change as the fit samples
/// them), and each vertex sums its list in that order. The bits are then the same for
/// any thread count and any chunking, with no per-thread (V, 12) buffers to clear and
/// merge — those would cost O(chunks·V) where this costs O(N + V).
pub fn lift_backward<T: Real>(
    inputs: &LiftInputs<'_, T>,
    grads: &LiftGradOutputs<'_, T>,
    needs: &LiftNeeds,
) -> Result<LiftGrads<T>> {
    let (n, v) = inputs.validate()?;
    let layout = |text: &str| format!("{text} with N = {n}");
    if let Some(g) = grads.v_means {
        check_len("v_means", g, n * 3, &layout("(N, 3)"))?;
    }
    if let Some(g) = grads.v_normals {
        check_len("v_normals", g, n * 3, &layout("(N, 3)"))?;
    }
    if let Some(g) = grads.v_quats {
        check_len("v_quats", g, n * 4, &layout("(N, 4)"))?;
    }
    // Per Gaussian: ∂L/∂m (N, 3) for the posed normal before normalising, m = frame·rest
    // (∂L/∂frame = ∂L/∂m ⊗ rest is formed in the vertex gather, not stored: a third of
    // the memory), ∂L/∂rest normal (N, 3), ∂L/∂lift (N,).
    let per_gaussian = needs.rotations || needs.normals || needs.lift;
    let size = |len: usize| if per_gaussian { len } else { 0 };
    let mut v_posed = zeroed("lift posed-normal gradient", size(n * 3))?;
    let mut v_normals = zeroed("lift normal gradient", size(n * 3))?;
    let mut v_lift = zeroed("lift gradient", size(n))?;
    (
        v_posed.par_chunks_mut(CHUNK * 3),
        v_normals.par_chunks_mut(CHUNK * 3),
        v_lift.par_chunks_mut(CHUNK),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(c, (v_m, v_rest, v_lift))| {
            for j in 0..v_lift.len() {
                let i = c * CHUNK + j;
                let v_mean: V3<T> = row(grads.v_means, i);
                let v_out: V3<T> = row(grads.v_normals, i);
                let v_q: [T; 4] = row(grads.v_quats, i);
                let zero = T::zero();
                let mean_zero = v_mean.iter().all(|&g| g == zero);
                if mean_zero && v_out.iter().chain(&v_q).all(|&g| g == zero) {
                    continue; // culled or unseen: exactly zero (as the buffers are)
                }
                let p = inputs.posed(i);
                if !mean_zero {
                    v_lift[j] = dot(&v_mean, &p.normal);
                }
                let lift = inputs.lift[i];
                let from_quat = p.quat.backward(&v_q);
                let v_normal = map3(|k| lift * v_mean[k] + v_out[k] + from_quat[k]);
                if v_normal.iter().all(|&g| g == zero) {
                    continue;
                }
                let g = normalise_backward(&p.normal, p.length, &v_normal);
                v_rest[3 * j..3 * j + 3].copy_from_slice(&matvec_t(&p.frame, &g));
                v_m[3 * j..3 * j + 3].copy_from_slice(&g);
            }
        });
    let v_means = grads.v_means.filter(|_| needs.verts);
    let (v_verts, v_rotations) = if v_means.is_some() || needs.rotations {
        let corners = corners_by_vertex(inputs.face_verts, v)?;
        let mut v_verts = zeroed("vertex gradient", v * 3)?;
        let mut v_rotations = zeroed("rotation gradient", v * 9)?;
        let (bary, rest, v_posed) = (inputs.bary, inputs.normals, &v_posed);
        (
            v_verts.par_chunks_mut(VERTEX_CHUNK * 3),
            v_rotations.par_chunks_mut(VERTEX_CHUNK * 9),
        )
            .into_par_iter()
            .enumerate()
            .for_each(|(c, (dv, dr))| {
                for j in 0..dv.len() / 3 {
                    let list = corners.of(c * VERTEX_CHUNK + j);
                    if let Some(g) = v_means {
                        dv[3 * j..3 * j + 3].copy_from_slice(&gather::<T, 3>(list, bary, g));
                    }
                    if needs.rotations {
                        dr[9 * j..9 * j + 9].copy_from_slice(&gather_outer(list, bary, v_posed, rest));
                    }
                }
            });
        (
            needs.verts.then_some(v_verts),
            needs.rotations.then_some(v_rotations),
        )
    } else {
        (needs.verts.then(|| vec![T::zero(); v * 3]), None)
    };
    Ok(LiftGrads {
        v_verts,
        v_rotations,
        v_normals: needs.normals.then_some(v_normals),
        v_lift: needs.lift.then_some(v_lift),
    })
}

/// Σ over a vertex's corners `e = 3·g + k` of `bary[e]·(a[g] ⊗ b[g])` (3 × 3, row-major),
/// in list order; rows with `a[g] = 0` are skipped.
#[inline(always)]
fn gather_outer<T: Real>(corners: &[u32], bary: &[T], a: &[T], b: &[T]) -> [T; 9] {
    let mut acc = [T::zero(); 9];
    for &e in corners {
        let (w, g) = (bary[e as usize], e as usize / 3);
        let row = &a[3 * g..3 * g + 3];
        if row.iter().all(|&x| x == T::zero()) {
            continue; // no gradient: skipped, so a non-finite `b` row adds no 0·NaN
        }
        for r in 0..3 {
            let wa = w * row[r];
            for k in 0..3 {
                acc[3 * r + k] += wa * b[3 * g + k];
            }
        }
    }
    acc
}

/// Σ over a vertex's corners `e = 3·g + k` of `bary[e]·rows[g]`, in list order.
#[inline(always)]
fn gather<T: Real, const W: usize>(corners: &[u32], bary: &[T], rows: &[T]) -> [T; W] {
    let mut acc = [T::zero(); W];
    for &e in corners {
        let (w, g) = (bary[e as usize], e as usize / 3);
        for k in 0..W {
            acc[k] += w * rows[W * g + k];
        }
    }
    acc
}

/// Each vertex's Gaussian corners `3·g + k`, ascending, in CSR form.
struct CornerLists {
    /// (V + 1,) start of each vertex's list.
    offsets: Vec<u32>,
    /// (3N,) corner ids.
    entries: Vec<u32>,
}

/// Counting sort of the corners by vertex (indices already checked).
fn corners_by_vertex(face_verts: &[i32], num_verts: usize) -> Result<CornerLists> {
    let mut offsets: Vec<u32> = zeroed("lift vertex offsets", num_verts + 1)?;
    for &f in face_verts {
        offsets[f as usize + 1] += 1;
    }
    for k in 0..num_verts {
        offsets[k + 1] += offsets[k];
    }
    let mut cursor: Vec<u32> = zeroed("lift vertex cursor", num_verts)?;
    cursor.copy_from_slice(&offsets[..num_verts]);
    let mut entries: Vec<u32> = zeroed("lift vertex corners", face_verts.len())?;
    for (e, &f) in face_verts.iter().enumerate() {
        let slot = &mut cursor[f as usize];
        entries[*slot as usize] = e as u32;
        *slot += 1;
    }
    Ok(CornerLists { offsets, entries })
}

impl CornerLists {
    #[inline(always)]
    fn of(&self, vert: usize) -> &[u32] {
        &self.entries[self.offsets[vert] as usize..self.offsets[vert + 1] as usize]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{on_threads, Rng};

    /// Owned inputs: `n` Gaussians on a random mesh of `v` vertices.
    struct Case<T> {
        verts: Vec<T>,
        rotations: Vec<T>,
        face_verts: Vec<i32>,
        bary: Vec<T>,
        normals: Vec<T>,
        lift: Vec<T>,
        centre: Vec<T>,
    }

    impl<T: Real> Case<T> {
        fn new(n: usize, v: usize, seed: u64) -> Self {
            let mut rng = Rng::new(seed);
            let mut rotations = Vec::with_capacity(v * 9);
            for _ in 0..v {
                // Near-rotations: identity plus a perturbation (any matrix is valid input).
                for r in 0..3 {
                    for c in 0..3 {
                        let eye = if r == c { 1.0 } else { 0.0 };
                        rotations.push(T::c(eye + rng.uniform(-0.3, 0.3)));
                    }
                }
            }
            let face_verts = (0..n * 3).map(|_| (rng.next_u64() % v as u64) as i32).collect();
            let mut bary = Vec::with_capacity(n * 3);
            for _ in 0..n {
                let (a, b) = (rng.uniform(0.05, 0.9), rng.uniform(0.05, 0.9));
                let s = a + b + rng.uniform(0.05, 0.9);
                bary.extend([a / s, b / s, 1.0 - a / s - b / s].map(T::c));
            }
            Self {
                verts: rng.vec(v * 3, -0.1, 0.1),
                rotations,
                face_verts,
                bary,
                normals: rng.vec(n * 3, -1.0, 1.0),
                lift: rng.vec(n, -0.01, 0.01),
                centre: vec![T::c(0.05), T::c(-0.02), T::c(-1.0)],
            }
        }

        fn inputs(&self) -> LiftInputs<'_, T> {
            LiftInputs {
                verts: &self.verts,
                rotations: &self.rotations,
                face_verts: &self.face_verts,
                bary: &self.bary,
                normals: &self.normals,
                lift: &self.lift,
                centre: &self.centre,
            }
        }
    }

    const ALL: LiftNeeds = LiftNeeds {
        verts: true,
        rotations: true,
        normals: true,
        lift: true,
    };

    fn rotation_z_axis(q: [f64; 4]) -> [f64; 3] {
        let [w, x, y, z] = q;
        [
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ]
    }

    #[test]
    fn quaternions_point_local_z_along_the_normal() {
        let mut dirs = vec![
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [0.3, -0.2, 0.0],
        ];
        for eps in [1.0, 1e-3, 1e-8, 1e-20, 1e-300, 0.0] {
            dirs.push([eps, 0.0, -1.0]);
        }
        for scale in [1.0, 1e-30, 1e30, 1e-310] {
            for d in &dirs {
                let n = d.map(|x| x * scale);
                let q = Quat::of(n).q;
                let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
                assert!((norm - 1.0).abs() < 1e-12, "{n:?} → {q:?}");
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let z = rotation_z_axis(q);
                for k in 0..3 {
                    assert!((z[k] - d[k] / len).abs() < 1e-12, "{n:?} → z axis {z:?}");
                }
            }
        }
        for bad in [[0.0; 3], [f64::NAN, 0.0, 1.0], [f64::INFINITY, 0.0, 0.0]] {
            let q = Quat::of(bad);
            assert_eq!(q.q, [1.0, 0.0, 0.0, 0.0]);
            assert_eq!(q.backward(&[1.0, -2.0, 3.0, 4.0]), [0.0; 3]);
        }
    }

    #[test]
    fn forward_follows_the_definition() {
        let case = Case::<f64>::new(50, 7, 1);
        let out = lift_forward(&case.inputs()).unwrap();
        for i in 0..50 {
            let f: Vec<usize> = (0..3).map(|k| case.face_verts[3 * i + k] as usize).collect();
            let b = &case.bary[3 * i..3 * i + 3];
            let mut frame = [[0.0; 3]; 3];
            let mut surface = [0.0; 3];
            for k in 0..3 {
                for r in 0..3 {
                    surface[r] += b[k] * case.verts[3 * f[k] + r];
                    for c in 0..3 {
                        frame[r][c] += b[k] * case.rotations[9 * f[k] + 3 * r + c];
                    }
                }
            }
            let m = matvec(&frame, &map3(|k| case.normals[3 * i + k]));
            let len = dot(&m, &m).sqrt();
            for r in 0..3 {
                let n = m[r] / len;
                assert!((out.normals[3 * i + r] - n).abs() < 1e-14);
                assert!((out.means[3 * i + r] - (surface[r] + case.lift[i] * n)).abs() < 1e-14);
                for c in 0..3 {
                    assert_eq!(out.frames[9 * i + 3 * r + c], frame[r][c]);
                }
            }
            // The view direction: the camera ray taken back to the rest frame (frameᵀ).
            let ray = map3(|k| out.means[3 * i + k] - case.centre[k]);
            let local = matvec_t(&frame, &ray);
            let len = dot(&local, &local).sqrt();
            let dir = map3(|k| out.view_dirs[3 * i + k]);
            for k in 0..3 {
                assert!((dir[k] - local[k] / len).abs() < 1e-14);
            }
            assert!((dot(&dir, &dir) - 1.0).abs() < 1e-14);
        }
    }

    /// Σ of every differentiable output weighted by fixed random weights.
    fn loss(case: &Case<f64>, w: &(Vec<f64>, Vec<f64>, Vec<f64>)) -> f64 {
        let out = lift_forward(&case.inputs()).unwrap();
        let d = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        d(&out.means, &w.0) + d(&out.normals, &w.1) + d(&out.quats, &w.2)
    }

    #[test]
    fn backward_matches_central_differences() {
        let (n, v) = (40, 9);
        let mut case = Case::<f64>::new(n, v, 2);
        // Both quaternion branches, and Gaussians with one vertex weight 1.
        case.normals[2] = -0.9;
        case.normals[5] = 0.9;
        case.bary[6..9].copy_from_slice(&[1.0, 0.0, 0.0]);
        let mut rng = Rng::new(5);
        let w = (
            rng.vec(n * 3, -1.0, 1.0),
            rng.vec(n * 3, -1.0, 1.0),
            rng.vec(n * 4, -1.0, 1.0),
        );
        let grads = LiftGradOutputs {
            v_means: Some(&w.0),
            v_normals: Some(&w.1),
            v_quats: Some(&w.2),
        };
        let g = lift_backward(&case.inputs(), &grads, &ALL).unwrap();
        let h = 1e-6;
        type Field = fn(&mut Case<f64>) -> &mut Vec<f64>;
        let fields: [(&str, Field, &Vec<f64>); 4] = [
            ("verts", |c| &mut c.verts, g.v_verts.as_ref().unwrap()),
            ("rotations", |c| &mut c.rotations, g.v_rotations.as_ref().unwrap()),
            ("normals", |c| &mut c.normals, g.v_normals.as_ref().unwrap()),
            ("lift", |c| &mut c.lift, g.v_lift.as_ref().unwrap()),
        ];
        for (name, field, grad) in fields {
            for trial in 0..4 {
                let dir: Vec<f64> = rng.vec(grad.len(), -1.0, 1.0);
                let mut plus = Case { ..clone(&case) };
                let mut minus = Case { ..clone(&case) };
                for (k, d) in dir.iter().enumerate() {
                    field(&mut plus)[k] += h * d;
                    field(&mut minus)[k] -= h * d;
                }
                let fd = (loss(&plus, &w) - loss(&minus, &w)) / (2.0 * h);
                let analytic: f64 = grad.iter().zip(&dir).map(|(a, b)| a * b).sum();
                let err = (fd - analytic).abs() / analytic.abs().max(1.0);
                assert!(err < 1e-7, "{name} trial {trial}: fd {fd} vs {analytic}");
            }
        }
    }

    fn clone(c: &Case<f64>) -> Case<f64> {
        Case {
            verts: c.verts.clone(),
            rotations: c.rotations.clone(),
            face_verts: c.face_verts.clone(),
            bary: c.bary.clone(),
            normals: c.normals.clone(),
            lift: c.lift.clone(),
            centre: c.centre.clone(),
        }
    }

    #[test]
    fn same_bits_for_any_thread_count() {
        // Many Gaussians per vertex, several chunks.
        let (n, v) = (5000, 300);
        let case = Case::<f32>::new(n, v, 3);
        let mut rng = Rng::new(4);
        let w: (Vec<f32>, Vec<f32>, Vec<f32>) = (
            rng.vec(n * 3, -1.0, 1.0),
            rng.vec(n * 3, -1.0, 1.0),
            rng.vec(n * 4, -1.0, 1.0),
        );
        let run = |threads: usize| {
            on_threads(threads, || {
                let out = lift_forward(&case.inputs()).unwrap();
                let grads = LiftGradOutputs {
                    v_means: Some(&w.0),
                    v_normals: Some(&w.1),
                    v_quats: Some(&w.2),
                };
                let g = lift_backward(&case.inputs(), &grads, &ALL).unwrap();
                let bits = |x: &[f32]| x.iter().map(|y| y.to_bits()).collect::<Vec<_>>();
                [
                    bits(&out.means),
                    bits(&out.normals),
                    bits(&out.quats),
                    bits(&out.frames),
                    bits(&out.view_dirs),
                    bits(g.v_verts.as_ref().unwrap()),
                    bits(g.v_rotations.as_ref().unwrap()),
                    bits(g.v_normals.as_ref().unwrap()),
                    bits(g.v_lift.as_ref().unwrap()),
                ]
            })
        };
        let one = run(1);
        for threads in [2, 3, 4] {
            assert!(one == run(threads), "{threads} threads differ from 1");
        }
    }

    #[test]
    fn degenerate_normals_are_finite_and_pass_no_gradient_through_the_fallback() {
        let mut case = Case::<f32>::new(4, 5, 6);
        case.normals[0..3].copy_from_slice(&[0.0; 3]);
        case.normals[3..6].copy_from_slice(&[f32::NAN, 0.0, 1.0]);
        case.normals[6..9].copy_from_slice(&[1e30, -2e30, 5e29]);
        case.normals[9..12].copy_from_slice(&[1e-30, 0.0, -1e-30]);
        let out = lift_forward(&case.inputs()).unwrap();
        assert_eq!(&out.quats[0..8], &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
        assert_eq!(&out.normals[0..3], &[0.0; 3]);
        assert!(out.means[3..6].iter().all(|x| x.is_nan()));
        assert!(out.means[6..].iter().chain(&out.quats).all(|x| x.is_finite()));
        // The huge normal is normalised (no overflow to a zero normal).
        let n = &out.normals[6..9];
        assert!(((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) - 1.0).abs() < 1e-6);
        // The NaN Gaussian seen only through its (fallback) quaternion, the others
        // everywhere: every gradient finite, the NaN one's exactly zero.
        let mut v_means = vec![0.5f32; 12];
        v_means[3..6].copy_from_slice(&[0.0; 3]);
        let v_quats = vec![1.0f32; 16];
        let grads = LiftGradOutputs {
            v_means: Some(&v_means),
            v_normals: None,
            v_quats: Some(&v_quats),
        };
        let g = lift_backward(&case.inputs(), &grads, &ALL).unwrap();
        for x in [&g.v_verts, &g.v_rotations, &g.v_normals, &g.v_lift] {
            assert!(x.as_ref().unwrap().iter().all(|y| y.is_finite()), "{x:?}");
        }
        assert_eq!(&g.v_normals.as_ref().unwrap()[3..6], &[0.0; 3]);
        assert_eq!(g.v_lift.as_ref().unwrap()[1], 0.0);
        // No upstream gradient at all: exact zeros everywhere.
        let g = lift_backward(&case.inputs(), &LiftGradOutputs::default(), &ALL).unwrap();
        for x in [&g.v_verts, &g.v_rotations, &g.v_normals, &g.v_lift] {
            assert!(x.as_ref().unwrap().iter().all(|y| *y == 0.0));
        }
    }

    #[test]
    fn rejects_bad_arguments() {
        let case = Case::<f32>::new(6, 4, 7);
        let ok = case.inputs();
        assert!(lift_forward(&ok).is_ok());
        let mut faces = case.face_verts.clone();
        faces[7] = 4;
        let err = lift_forward(&LiftInputs {
            face_verts: &faces,
            ..ok
        })
        .unwrap_err();
        assert!(
            matches!(
                err,
                Error::IndexOutOfRange {
                    arg: "face_verts",
                    index: 7,
                    ..
                }
            ),
            "{err}"
        );
        faces[7] = -1;
        assert!(lift_forward(&LiftInputs {
            face_verts: &faces,
            ..ok
        })
        .is_err());
        let short = |arg: &str, e: Error| matches!(e, Error::Shape { arg: a, .. } if a == arg);
        assert!(short(
            "rotations",
            lift_forward(&LiftInputs {
                rotations: &case.rotations[1..],
                ..ok
            })
            .unwrap_err()
        ));
        assert!(short(
            "bary",
            lift_forward(&LiftInputs {
                bary: &case.bary[3..],
                ..ok
            })
            .unwrap_err()
        ));
        assert!(short(
            "normals",
            lift_forward(&LiftInputs {
                normals: &case.normals[..3],
                ..ok
            })
            .unwrap_err()
        ));
        assert!(short(
            "lift",
            lift_forward(&LiftInputs {
                lift: &case.lift[1..],
                ..ok
            })
            .unwrap_err()
        ));
        assert!(short(
            "centre",
            lift_forward(&LiftInputs {
                centre: &case.centre[1..],
                ..ok
            })
            .unwrap_err()
        ));
        assert!(short(
            "verts",
            lift_forward(&LiftInputs {
                verts: &[],
                rotations: &[],
                ..ok
            })
            .unwrap_err()
        ));
        let mut verts = case.verts.clone();
        verts[2] = f32::INFINITY;
        let err = lift_forward(&LiftInputs { verts: &verts, ..ok }).unwrap_err();
        assert!(matches!(err, Error::NonFinite { arg: "verts", .. }));
        let grads = LiftGradOutputs {
            v_quats: Some(&[0.0; 23]),
            ..Default::default()
        };
        assert!(short("v_quats", lift_backward(&ok, &grads, &ALL).unwrap_err()));
        // No Gaussians: empty outputs, zero vertex gradients.
        let empty = LiftInputs {
            face_verts: &[],
            bary: &[],
            normals: &[],
            lift: &[],
            ..ok
        };
        assert!(lift_forward(&empty).unwrap().means.is_empty());
        let g = lift_backward(&empty, &LiftGradOutputs::default(), &ALL).unwrap();
        assert_eq!(g.v_verts.unwrap(), vec![0.0; 12]);
    }
}
