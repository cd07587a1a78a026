//! LBS backward: the adjoint of [`super::lbs_forward`], computing only the gradients asked
//! for. Two parallel passes over vertex chunks (skinning, then shape) around a serial pass
//! over the kinematic chain; partial sums are merged in chunk order.

use rayon::prelude::*;

use super::skeleton::Skeleton;
use super::{LbsInputs, LbsModel, VERT_CHUNK};
use crate::error::{check_len, Result};
use crate::mat3::{add, frobenius, map3, matmul_nt, matmul_tn, matvec_t, outer, zero3, M3, V3};
use crate::memory::zeroed;
use crate::parallel::{axpy, batch_chunks_mut, dot, optional_chunks, sum_in_order};
use crate::Real;

/// Gradients of the loss with respect to the forward outputs; `None` means zero.
#[derive(Debug, Clone, Copy, Default)]
pub struct LbsGradOutputs<'a, T> {
    /// `(B, V, 3)`
    pub v_verts: Option<&'a [T]>,
    /// `(B, J, 3)`
    pub v_joints: Option<&'a [T]>,
    /// `(B, V, 3, 3)`
    pub v_rotations: Option<&'a [T]>,
}

/// Which input gradients to compute. Work for the others is skipped.
#[derive(Debug, Clone, Copy, Default)]
pub struct LbsNeeds {
    pub betas: bool,
    pub pose: bool,
    pub transl: bool,
    pub v_template: bool,
    pub shapedirs: bool,
}

/// Input gradients; a field is `Some` exactly when it was asked for in [`LbsNeeds`].
#[derive(Debug, Clone, Default)]
pub struct LbsGrads<T> {
    /// `(B, NB)`
    pub v_betas: Option<Vec<T>>,
    /// `(B, J·3)`
    pub v_pose: Option<Vec<T>>,
    /// `(B, 3)`
    pub v_transl: Option<Vec<T>>,
    /// `(V, 3)`, summed over the batch.
    pub v_template: Option<Vec<T>>,
    /// `(V, 3, NB)`, summed over the batch.
    pub v_shapedirs: Option<Vec<T>>,
}

/// What the backward needs from the forward (borrowed from [`super::LbsForward`] or from
/// tensors saved by an autograd wrapper).
#[derive(Debug, Clone, Copy)]
pub struct LbsSaved<'a, T> {
    /// `(B, V, 3)`
    pub v_shaped: &'a [T],
    /// `(B, V, 3)`
    pub v_posed: &'a [T],
    /// `(B, J, 3)`
    pub rest_joints: &'a [T],
}

/// Per-chunk partial sums of the skinning pass, for one batch element.
struct SkinPartials<T> {
    /// ∂L/∂A_j: rotation part and translation part.
    a_rot: Vec<M3<T>>,
    a_t: Vec<V3<T>>,
    pose_feats: Vec<T>,
    transl: V3<T>,
}

pub fn lbs_backward<T: Real>(
    model: &LbsModel<T>,
    inputs: &LbsInputs<T>,
    saved: &LbsSaved<T>,
    grads: &LbsGradOutputs<T>,
    needs: &LbsNeeds,
) -> Result<LbsGrads<T>> {
    inputs.validate(model)?;
    let (b, nv, nj, np) = (
        inputs.batch,
        model.num_verts,
        model.num_joints,
        model.num_pose_feats(),
    );
    check_len("v_shaped", saved.v_shaped, b * nv * 3, "(B, V, 3)")?;
    check_len("v_posed", saved.v_posed, b * nv * 3, "(B, V, 3)")?;
    check_len("rest_joints", saved.rest_joints, b * nj * 3, "(B, J, 3)")?;
    for (arg, g, row) in [
        ("v_verts", grads.v_verts, 3),
        ("v_joints", grads.v_joints, 0),
        ("v_rotations", grads.v_rotations, 9),
    ] {
        let expected = if row == 0 { b * nj * 3 } else { b * nv * row };
        if let Some(g) = g {
            check_len(arg, g, expected, "the shape of the matching forward output")?;
        }
    }
    let shape_needed = needs.betas || needs.v_template || needs.shapedirs;
    let skeletons: Vec<Skeleton<T>> = (0..b)
        .map(|bi| {
            Skeleton::new(
                model.parents,
                &saved.rest_joints[bi * nj * 3..(bi + 1) * nj * 3],
                &inputs.pose[bi * nj * 3..(bi + 1) * nj * 3],
                needs.pose,
            )
        })
        .collect();

    // Pass 1: skinning adjoint, per vertex chunk.
    let mut v_posed_grad = zeroed("posed vertex gradient (B, V, 3)", b * nv * 3)?;
    let chunk_partials: Vec<Vec<SkinPartials<T>>> = batch_chunks_mut(&mut v_posed_grad, b, 3, VERT_CHUNK)
        .into_par_iter()
        .enumerate()
        .map(|(chunk, mut gposed)| {
            let start = chunk * VERT_CHUNK;
            let len = gposed[0].len() / 3;
            (0..b)
                .map(|bi| {
                    let mut part = SkinPartials {
                        a_rot: vec![zero3(); nj],
                        a_t: vec![[T::zero(); 3]; nj],
                        pose_feats: vec![T::zero(); np],
                        transl: [T::zero(); 3],
                    };
                    for i in 0..len {
                        let v = start + i;
                        let gv: V3<T> = match grads.v_verts {
                            Some(g) => map3(|c| g[(bi * nv + v) * 3 + c]),
                            None => [T::zero(); 3],
                        };
                        let posed: V3<T> = map3(|c| saved.v_posed[(bi * nv + v) * 3 + c]);
                        // ∂L/∂(blended rotation) = g_v ⊗ v_posed + ∂L/∂rotations
                        let mut g_rot = outer(&gv, &posed);
                        if let Some(gr) = grads.v_rotations {
                            let o = (bi * nv + v) * 9;
                            g_rot = add(&g_rot, &map3(|r| map3(|c| gr[o + r * 3 + c])));
                        }
                        let weights = &model.lbs_weights[v * nj..(v + 1) * nj];
                        let (rot, _) = skeletons[bi].blend(weights);
                        let gp = matvec_t(&rot, &gv);
                        gposed[bi][i * 3..i * 3 + 3].copy_from_slice(&gp);
                        for (j, &w) in weights.iter().enumerate() {
                            if w == T::zero() {
                                continue;
                            }
                            for r in 0..3 {
                                for c in 0..3 {
                                    part.a_rot[j][r][c] += w * g_rot[r][c];
                                }
                                part.a_t[j][r] += w * gv[r];
                            }
                        }
                        for c in 0..3 {
                            part.transl[c] += gv[c];
                        }
                    }
                    if needs.pose {
                        for p in 0..np {
                            let row = &model.posedirs[p * nv * 3 + start * 3..p * nv * 3 + (start + len) * 3];
                            part.pose_feats[p] = dot(row, gposed[bi]);
                        }
                    }
                    part
                })
                .collect()
        })
        .collect();

    let mut out = LbsGrads::default();
    let mut v_pose = vec![T::zero(); b * nj * 3];
    let mut v_transl = vec![T::zero(); b * 3];
    let mut v_rest_joints = vec![T::zero(); b * nj * 3];
    for bi in 0..b {
        let s = &skeletons[bi];
        let mut g_a_rot = vec![zero3::<T>(); nj];
        let mut g_a_t = vec![[T::zero(); 3]; nj];
        let mut g_pf = vec![T::zero(); np];
        for chunk in &chunk_partials {
            let p = &chunk[bi];
            for j in 0..nj {
                g_a_rot[j] = add(&g_a_rot[j], &p.a_rot[j]);
                for c in 0..3 {
                    g_a_t[j][c] += p.a_t[j][c];
                }
            }
            for k in 0..np {
                g_pf[k] += p.pose_feats[k];
            }
            for c in 0..3 {
                v_transl[bi * 3 + c] += p.transl[c];
            }
        }
        let rest = &saved.rest_joints[bi * nj * 3..(bi + 1) * nj * 3];
        let joint = |j: usize| -> V3<T> { map3(|c| rest[j * 3 + c]) };
        // A_j = [R_Gj | t_Gj − R_Gj J_j]; posed joints = t_Gj + transl.
        let mut g_grot = vec![zero3::<T>(); nj];
        let mut g_gt = vec![[T::zero(); 3]; nj];
        let g_rest = &mut v_rest_joints[bi * nj * 3..(bi + 1) * nj * 3];
        for j in 0..nj {
            let jj = joint(j);
            g_grot[j] = add(&g_a_rot[j], &outer(&g_a_t[j], &jj).map(|r| r.map(|x| -x)));
            let gj = grads.v_joints.map(|g| map3(|c| g[(bi * nj + j) * 3 + c]));
            for c in 0..3 {
                let from_joint = gj.map_or(T::zero(), |g| g[c]);
                g_gt[j][c] = g_a_t[j][c] + from_joint;
                v_transl[bi * 3 + c] += from_joint;
            }
            let d = matvec_t(&s.global_rot[j], &g_a_t[j]);
            for c in 0..3 {
                g_rest[j * 3 + c] -= d[c];
            }
        }
        // Kinematic chain, leaves to root: G_j = G_p · [R_j | rel_j].
        let mut g_local = vec![zero3::<T>(); nj];
        for j in (0..nj).rev() {
            let g_rel;
            if j == 0 {
                g_local[0] = g_grot[0];
                g_rel = g_gt[0];
            } else {
                let p = model.parents[j] as usize;
                g_local[j] = matmul_tn(&s.global_rot[p], &g_grot[j]);
                g_rel = matvec_t(&s.global_rot[p], &g_gt[j]);
                let from_rot = matmul_nt(&g_grot[j], &s.local[j]);
                let from_t = outer(&g_gt[j], &s.rel[j]);
                g_grot[p] = add(&add(&g_grot[p], &from_rot), &from_t);
                for c in 0..3 {
                    let child = g_gt[j][c];
                    g_gt[p][c] += child;
                    g_rest[p * 3 + c] -= g_rel[c];
                }
            }
            for c in 0..3 {
                g_rest[j * 3 + c] += g_rel[c];
            }
        }
        if needs.pose {
            for j in 0..nj {
                let mut g = g_local[j];
                if j > 0 {
                    for r in 0..3 {
                        for c in 0..3 {
                            g[r][c] += g_pf[(j - 1) * 9 + r * 3 + c];
                        }
                    }
                }
                for k in 0..3 {
                    v_pose[(bi * nj + j) * 3 + k] = frobenius(&s.local_jacobian[j][k], &g);
                }
            }
        }
    }
    if needs.pose {
        out.v_pose = Some(v_pose);
    }
    if needs.transl {
        out.v_transl = Some(v_transl);
    }
    if shape_needed {
        shape_backward(model, inputs, &v_posed_grad, &v_rest_joints, needs, &mut out);
    }
    Ok(out)
}

/// Pass 2: ∂L/∂v_shaped = ∂L/∂v_posed + J_regressorᵀ·∂L/∂J, then through the blendshapes.
fn shape_backward<T: Real>(
    model: &LbsModel<T>,
    inputs: &LbsInputs<T>,
    v_posed_grad: &[T],
    v_rest_joints: &[T],
    needs: &LbsNeeds,
    out: &mut LbsGrads<T>,
) {
    let (b, nv, nb, nj) = (inputs.batch, model.num_verts, model.num_betas, model.num_joints);
    let mut v_template = vec![T::zero(); if needs.v_template { nv * 3 } else { 0 }];
    let mut v_shapedirs = vec![T::zero(); if needs.shapedirs { nv * 3 * nb } else { 0 }];
    let tasks = nv.div_ceil(VERT_CHUNK);
    let template_chunks = optional_chunks(
        needs.v_template.then_some(v_template.as_mut_slice()),
        VERT_CHUNK * 3,
        tasks,
    );
    let shapedirs_chunks = optional_chunks(
        needs.shapedirs.then_some(v_shapedirs.as_mut_slice()),
        VERT_CHUNK * 3 * nb,
        tasks,
    );
    let partial_betas: Vec<Vec<T>> = template_chunks
        .into_par_iter()
        .zip(shapedirs_chunks)
        .enumerate()
        .map(|(chunk, (mut tmpl, mut sdirs))| {
            let start = chunk * VERT_CHUNK;
            let len = VERT_CHUNK.min(nv - start);
            let mut betas = vec![T::zero(); if needs.betas { b * nb } else { 0 }];
            let mut g_shaped = vec![T::zero(); b];
            for i in 0..len {
                let v = start + i;
                for c in 0..3 {
                    for bi in 0..b {
                        let mut g = v_posed_grad[(bi * nv + v) * 3 + c];
                        for j in 0..nj {
                            g += model.j_regressor[j * nv + v] * v_rest_joints[(bi * nj + j) * 3 + c];
                        }
                        g_shaped[bi] = g;
                    }
                    if let Some(t) = tmpl.as_deref_mut() {
                        t[i * 3 + c] = g_shaped.iter().copied().sum();
                    }
                    let row = &model.shapedirs[(v * 3 + c) * nb..(v * 3 + c + 1) * nb];
                    if needs.betas {
                        for bi in 0..b {
                            axpy(g_shaped[bi], row, &mut betas[bi * nb..(bi + 1) * nb]);
                        }
                    }
                    if let Some(sd) = sdirs.as_deref_mut() {
                        let dst = &mut sd[(i * 3 + c) * nb..(i * 3 + c + 1) * nb];
                        for bi in 0..b {
                            axpy(g_shaped[bi], &inputs.betas[bi * nb..(bi + 1) * nb], dst);
                        }
                    }
                }
            }
            betas
        })
        .collect();
    if needs.betas {
        out.v_betas = Some(sum_in_order(&partial_betas, b * nb));
    }
    if needs.v_template {
        out.v_template = Some(v_template);
    }
    if needs.shapedirs {
        out.v_shapedirs = Some(v_shapedirs);
    }
}
