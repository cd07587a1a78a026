//! LBS forward: shape blendshapes → joint regression → skeleton → pose correctives →
//! blended skinning → translation.

use rayon::prelude::*;

use super::backward::LbsSaved;
use super::skeleton::Skeleton;
use super::{LbsInputs, LbsModel, VERT_CHUNK};
use crate::error::{check_finite, Result};
use crate::mat3::map3;
use crate::memory::zeroed;
use crate::parallel::{axpy, batch_chunks_mut, dot, sum_in_order};
use crate::Real;

/// Outputs of [`lbs_forward`]; the last three fields are the state the backward needs.
#[derive(Debug, Clone)]
pub struct LbsForward<T> {
    /// Posed, translated vertices `(B, V, 3)`.
    pub verts: Vec<T>,
    /// Posed, translated joints `(B, J, 3)`.
    pub joints: Vec<T>,
    /// Linear part of each vertex's blended skinning transform `(B, V, 3, 3)`. It carries
    /// rest-pose directions (normals) into the posed frame; it is a blend of rotations, so
    /// re-normalise the directions it maps.
    pub rotations: Vec<T>,
    /// Shaped template `(B, V, 3)`, saved for the backward.
    pub v_shaped: Vec<T>,
    /// Shaped template plus pose correctives `(B, V, 3)`, saved for the backward.
    pub v_posed: Vec<T>,
    /// Joints regressed from the shaped template `(B, J, 3)`, saved for the backward.
    pub rest_joints: Vec<T>,
}

impl<T> LbsForward<T> {
    /// The state [`super::lbs_backward`] needs, borrowed.
    pub fn saved(&self) -> LbsSaved<'_, T> {
        LbsSaved {
            v_shaped: &self.v_shaped,
            v_posed: &self.v_posed,
            rest_joints: &self.rest_joints,
        }
    }
}

/// Runs skinning for a batch. Errors name the first invalid argument; no work is done
/// before validation.
pub fn lbs_forward<T: Real>(model: &LbsModel<T>, inputs: &LbsInputs<T>) -> Result<LbsForward<T>> {
    inputs.validate(model)?;
    let (b, nv, nj) = (inputs.batch, model.num_verts, model.num_joints);
    let (v_shaped, rest_joints) = shape(model, inputs);
    let skeletons: Vec<Skeleton<T>> = (0..b)
        .map(|bi| {
            Skeleton::new(
                model.parents,
                &rest_joints[bi * nj * 3..(bi + 1) * nj * 3],
                &inputs.pose[bi * nj * 3..(bi + 1) * nj * 3],
                false,
            )
        })
        .collect();
    let pose_feats: Vec<Vec<T>> = skeletons.iter().map(Skeleton::pose_features).collect();
    let zero_transl = vec![T::zero(); b * 3];
    let transl = inputs.transl.unwrap_or(&zero_transl);

    let mut v_posed = zeroed("posed vertices (B, V, 3)", b * nv * 3)?;
    let mut verts = zeroed("vertices (B, V, 3)", b * nv * 3)?;
    let mut rotations = zeroed("vertex rotations (B, V, 3, 3)", b * nv * 9)?;
    batch_chunks_mut(&mut v_posed, b, 3, VERT_CHUNK)
        .into_par_iter()
        .zip(batch_chunks_mut(&mut verts, b, 3, VERT_CHUNK))
        .zip(batch_chunks_mut(&mut rotations, b, 9, VERT_CHUNK))
        .enumerate()
        .for_each(|(chunk, ((mut posed, mut out), mut rots))| {
            let start = chunk * VERT_CHUNK;
            let len = posed[0].len() / 3;
            // Pose correctives: rows of posedirs restricted to this chunk are contiguous.
            for bi in 0..b {
                let shaped = &v_shaped[(bi * nv + start) * 3..(bi * nv + start + len) * 3];
                posed[bi].copy_from_slice(shaped);
            }
            for p in 0..model.num_pose_feats() {
                let row = &model.posedirs[p * nv * 3 + start * 3..p * nv * 3 + (start + len) * 3];
                for bi in 0..b {
                    axpy(pose_feats[bi][p], row, posed[bi]);
                }
            }
            for i in 0..len {
                let weights = &model.lbs_weights[(start + i) * nj..(start + i + 1) * nj];
                for bi in 0..b {
                    let (rot, t) = skeletons[bi].blend(weights);
                    let v = &posed[bi][i * 3..i * 3 + 3];
                    for r in 0..3 {
                        out[bi][i * 3 + r] = rot[r][0] * v[0]
                            + rot[r][1] * v[1]
                            + rot[r][2] * v[2]
                            + t[r]
                            + transl[bi * 3 + r];
                        for c in 0..3 {
                            rots[bi][i * 9 + r * 3 + c] = rot[r][c];
                        }
                    }
                }
            }
        });

    let joints = skeletons
        .iter()
        .enumerate()
        .flat_map(|(bi, s)| {
            s.global_t
                .iter()
                .flat_map(move |t| map3(|c| t[c] + transl[bi * 3 + c]))
        })
        .collect();
    if check_finite("verts", &verts).is_err() {
        model.find_non_finite()?;
    }
    Ok(LbsForward {
        verts,
        joints,
        rotations,
        v_shaped,
        v_posed,
        rest_joints,
    })
}

/// Shaped template `(B,V,3)` and rest joints `(B,J,3)`, in one pass over `shapedirs`
/// (each row is read once for the whole batch; joints reduced per chunk, in chunk order).
fn shape<T: Real>(model: &LbsModel<T>, inputs: &LbsInputs<T>) -> (Vec<T>, Vec<T>) {
    let (b, nv, nb, nj) = (inputs.batch, model.num_verts, model.num_betas, model.num_joints);
    let mut v_shaped = vec![T::zero(); b * nv * 3];
    let partial_joints: Vec<Vec<T>> = batch_chunks_mut(&mut v_shaped, b, 3, VERT_CHUNK)
        .into_par_iter()
        .enumerate()
        .map(|(chunk, mut shaped)| {
            let start = chunk * VERT_CHUNK;
            let len = shaped[0].len() / 3;
            let mut joints = vec![T::zero(); b * nj * 3];
            for i in 0..len {
                let v = start + i;
                for c in 0..3 {
                    let row = &model.shapedirs[(v * 3 + c) * nb..(v * 3 + c + 1) * nb];
                    for bi in 0..b {
                        let x = model.v_template[v * 3 + c] + dot(row, &inputs.betas[bi * nb..(bi + 1) * nb]);
                        shaped[bi][i * 3 + c] = x;
                        for j in 0..nj {
                            joints[(bi * nj + j) * 3 + c] += model.j_regressor[j * nv + v] * x;
                        }
                    }
                }
            }
            joints
        })
        .collect();
    (v_shaped, sum_in_order(&partial_joints, b * nj * 3))
}
