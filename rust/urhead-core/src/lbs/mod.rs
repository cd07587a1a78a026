//! FLAME / SMPL linear blend skinning with a hand-written adjoint.
//!
//! Same math and argument meaning as the `lbs` function of the SMPL/FLAME code bases:
//! shape blendshapes, joints regressed from the shaped template, pose-corrective
//! blendshapes from flattened (R_j − I) of the non-root joints, a kinematic chain and
//! blended rigid transforms; translation is added after skinning.
//!
//! Shapes (row-major): `v_template (V,3)`, `shapedirs (V,3,NB)`, `posedirs (P, V·3)` with
//! `P = 9·(J−1)`, `j_regressor (J,V)` dense, `parents (J)` with `parents[0] = −1` and
//! `parents[j] < j`, `lbs_weights (V,J)`, `betas (B,NB)`, `pose (B, J·3)`, `transl (B,3)`.

mod backward;
mod forward;
pub mod rodrigues;
mod skeleton;

pub use backward::{lbs_backward, LbsGradOutputs, LbsGrads, LbsNeeds, LbsSaved};
pub use forward::{lbs_forward, LbsForward};

use crate::error::{check_finite, check_len, Error, Result};
use crate::Real;

/// Vertices per parallel work item. Fixed, so reductions are thread-count independent.
const VERT_CHUNK: usize = 128;

/// The constant tables of a skinned head model, borrowed from the caller.
#[derive(Debug, Clone, Copy)]
pub struct LbsModel<'a, T> {
    pub v_template: &'a [T],
    pub shapedirs: &'a [T],
    pub posedirs: &'a [T],
    pub j_regressor: &'a [T],
    pub parents: &'a [i32],
    pub lbs_weights: &'a [T],
    pub num_verts: usize,
    pub num_betas: usize,
    pub num_joints: usize,
}

impl<'a, T: Real> LbsModel<'a, T> {
    /// Checks that every table matches `(num_verts, num_betas, num_joints)` and that
    /// `parents` describes a tree in topological order. Cheap: the large tables are
    /// checked for finiteness only if an output turns out non-finite ([`Self::find_non_finite`]).
    pub fn new(
        v_template: &'a [T],
        shapedirs: &'a [T],
        posedirs: &'a [T],
        j_regressor: &'a [T],
        parents: &'a [i32],
        lbs_weights: &'a [T],
        num_verts: usize,
        num_betas: usize,
        num_joints: usize,
    ) -> Result<Self> {
        let (v, nb, j) = (num_verts, num_betas, num_joints);
        if v == 0 || j == 0 {
            return Err(Error::Shape {
                arg: "v_template",
                expected: "a non-empty mesh with at least one joint".into(),
                got: format!("V = {v}, J = {j}"),
            });
        }
        check_len("v_template", v_template, v * 3, &format!("(V, 3) with V = {v}"))?;
        check_len(
            "shapedirs",
            shapedirs,
            v * 3 * nb,
            &format!("(V, 3, NB) = ({v}, 3, {nb})"),
        )?;
        let p = 9 * (j - 1);
        check_len(
            "posedirs",
            posedirs,
            p * v * 3,
            &format!("(9·(J−1), V·3) = ({p}, {})", v * 3),
        )?;
        check_len("j_regressor", j_regressor, j * v, &format!("(J, V) = ({j}, {v})"))?;
        check_len("parents", parents, j, &format!("(J,) = ({j},)"))?;
        check_len("lbs_weights", lbs_weights, v * j, &format!("(V, J) = ({v}, {j})"))?;
        if parents[0] != -1 {
            return Err(Error::Invalid {
                arg: "parents",
                reason: format!("parents[0] must be -1 (the root), got {}", parents[0]),
            });
        }
        if let Some(k) = (1..j).find(|&k| !(0..k as i32).contains(&parents[k])) {
            return Err(Error::Invalid {
                arg: "parents",
                reason: format!(
                    "parents[{k}] = {} must be in [0, {k}) (joints in topological order)",
                    parents[k]
                ),
            });
        }
        check_finite("v_template", v_template)?;
        Ok(Self {
            v_template,
            shapedirs,
            posedirs,
            j_regressor,
            parents,
            lbs_weights,
            num_verts,
            num_betas,
            num_joints,
        })
    }

    /// Number of pose-corrective features, 9·(J−1).
    pub fn num_pose_feats(&self) -> usize {
        9 * (self.num_joints - 1)
    }

    /// Names the first large table holding NaN or infinity. Called only after a result
    /// came out non-finite, so valid inputs never pay for scanning 6M shapedirs floats.
    pub fn find_non_finite(&self) -> Result<()> {
        check_finite("shapedirs", self.shapedirs)?;
        check_finite("posedirs", self.posedirs)?;
        check_finite("j_regressor", self.j_regressor)?;
        check_finite("lbs_weights", self.lbs_weights)
    }
}

/// The per-call inputs: identity/expression coefficients, joint rotations, translation.
#[derive(Debug, Clone, Copy)]
pub struct LbsInputs<'a, T> {
    pub betas: &'a [T],
    pub pose: &'a [T],
    pub transl: Option<&'a [T]>,
    pub batch: usize,
}

impl<T: Real> LbsInputs<'_, T> {
    fn validate(&self, model: &LbsModel<T>) -> Result<()> {
        let (b, nb, j) = (self.batch, model.num_betas, model.num_joints);
        check_len("betas", self.betas, b * nb, &format!("(B, NB) = ({b}, {nb})"))?;
        check_len(
            "pose",
            self.pose,
            b * j * 3,
            &format!("(B, J·3) = ({b}, {})", j * 3),
        )?;
        check_finite("betas", self.betas)?;
        check_finite("pose", self.pose)?;
        if let Some(t) = self.transl {
            check_len("transl", t, b * 3, &format!("(B, 3) = ({b}, 3)"))?;
            check_finite("transl", t)?;
        }
        Ok(())
    }
}
