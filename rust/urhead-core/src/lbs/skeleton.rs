//! Per-batch-element joint state shared by the forward and the backward: local joint
//! rotations, the kinematic chain and the relative transforms A_j = G_j·[I | −J_j].

use super::rodrigues::{rotation, rotation_with_jacobian};
use crate::mat3::{eye3, matmul, matvec, M3, V3};
use crate::Real;

pub(super) struct Skeleton<T> {
    /// Local joint rotations R_j.
    pub local: Vec<M3<T>>,
    /// ∂R_j/∂ω_jk, filled only when the pose gradient is needed.
    pub local_jacobian: Vec<[M3<T>; 3]>,
    /// Joint offsets from the parent in rest pose (the root's is its position).
    pub rel: Vec<V3<T>>,
    /// Global joint rotations and translations G_j.
    pub global_rot: Vec<M3<T>>,
    pub global_t: Vec<V3<T>>,
    /// Skinning transforms A_j: rotation = G_j rotation, translation = t_Gj − R_Gj·J_j.
    pub a_t: Vec<V3<T>>,
}

impl<T: Real> Skeleton<T> {
    /// `rest_joints (J,3)`, `pose (J·3)`.
    pub fn new(parents: &[i32], rest_joints: &[T], pose: &[T], with_jacobian: bool) -> Self {
        let nj = parents.len();
        let joint = |j: usize| -> V3<T> { [0, 1, 2].map(|c| rest_joints[j * 3 + c]) };
        let mut local = Vec::with_capacity(nj);
        let mut local_jacobian = Vec::with_capacity(if with_jacobian { nj } else { 0 });
        for j in 0..nj {
            let w = [pose[j * 3], pose[j * 3 + 1], pose[j * 3 + 2]];
            if with_jacobian {
                let (r, jac) = rotation_with_jacobian(&w);
                local.push(r);
                local_jacobian.push(jac);
            } else {
                local.push(rotation(&w));
            }
        }
        let mut rel = Vec::with_capacity(nj);
        let mut global_rot: Vec<M3<T>> = Vec::with_capacity(nj);
        let mut global_t: Vec<V3<T>> = Vec::with_capacity(nj);
        for j in 0..nj {
            let jp = joint(j);
            if j == 0 {
                rel.push(jp);
                global_rot.push(local[0]);
                global_t.push(jp);
            } else {
                let p = parents[j] as usize;
                let parent_joint = joint(p);
                let r: V3<T> = [0, 1, 2].map(|c| jp[c] - parent_joint[c]);
                let rot = matmul(&global_rot[p], &local[j]);
                let off = matvec(&global_rot[p], &r);
                let t = [0, 1, 2].map(|c| global_t[p][c] + off[c]);
                rel.push(r);
                global_rot.push(rot);
                global_t.push(t);
            }
        }
        // a_j = t_Gj − R_Gj·J_j, accumulated down the chain as a_p + (R_Gp − R_Gj)·J_j: the
        // same value, but exactly zero when the rotations are identities (zero pose gives
        // the shaped template bit for bit) and its rounding scales with the rotation, not |J|.
        let mut a_t: Vec<V3<T>> = Vec::with_capacity(nj);
        for j in 0..nj {
            let jp = joint(j);
            if j == 0 {
                let rj = matvec(&global_rot[0], &jp);
                a_t.push([0, 1, 2].map(|c| jp[c] - rj[c]));
            } else {
                let p = parents[j] as usize;
                let diff = [0, 1, 2].map(|r| [0, 1, 2].map(|c| global_rot[p][r][c] - global_rot[j][r][c]));
                let d = matvec(&diff, &jp);
                a_t.push([0, 1, 2].map(|c| a_t[p][c] + d[c]));
            }
        }
        Self {
            local,
            local_jacobian,
            rel,
            global_rot,
            global_t,
            a_t,
        }
    }

    /// Pose-corrective features: flattened (R_j − I) of the non-root joints.
    pub fn pose_features(&self) -> Vec<T> {
        let eye: M3<T> = eye3();
        let mut f = Vec::with_capacity(9 * (self.local.len().saturating_sub(1)));
        for r in &self.local[1..] {
            for i in 0..3 {
                for k in 0..3 {
                    f.push(r[i][k] - eye[i][k]);
                }
            }
        }
        f
    }

    /// Blended skinning transform of one vertex: (Σ w_j R_Gj, Σ w_j a_j).
    #[inline]
    pub fn blend(&self, weights: &[T]) -> (M3<T>, V3<T>) {
        let mut rot = [[T::zero(); 3]; 3];
        let mut t = [T::zero(); 3];
        for (j, &w) in weights.iter().enumerate() {
            if w == T::zero() {
                continue;
            }
            for r in 0..3 {
                for c in 0..3 {
                    rot[r][c] += w * self.global_rot[j][r][c];
                }
                t[r] += w * self.a_t[j][r];
            }
        }
        (rot, t)
    }
}
