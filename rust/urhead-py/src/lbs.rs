//! Binding of `urhead_core::lbs`: each entry point serves float32 and float64 through one
//! generic body.

use numpy::{Element, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::lbs::{self as core, LbsGradOutputs, LbsInputs, LbsModel, LbsNeeds, LbsSaved};
use urhead_core::Real;

use crate::arrays::{array, data, optional, optional_array, optional_data, shape, with_float_type};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// The model tables, borrowed from numpy.
struct Tables<'py, T: Element> {
    v_template: Arr<'py, T>,
    shapedirs: Arr<'py, T>,
    posedirs: Arr<'py, T>,
    j_regressor: Arr<'py, T>,
    parents: Arr<'py, i32>,
    lbs_weights: Arr<'py, T>,
}

impl<T: Element + Real> Tables<'_, T> {
    fn model(&self) -> PyResult<LbsModel<'_, T>> {
        let v = shape(&self.v_template, "v_template", 2, "(V, 3)")?[0];
        let sd = shape(&self.shapedirs, "shapedirs", 3, "(V, 3, NB)")?;
        let j = shape(&self.j_regressor, "j_regressor", 2, "(J, V)")?[0];
        shape(&self.posedirs, "posedirs", 2, "(9·(J−1), V·3)")?;
        shape(&self.lbs_weights, "lbs_weights", 2, "(V, J)")?;
        shape(&self.parents, "parents", 1, "(J,)")?;
        LbsModel::new(
            data(&self.v_template, "v_template")?,
            data(&self.shapedirs, "shapedirs")?,
            data(&self.posedirs, "posedirs")?,
            data(&self.j_regressor, "j_regressor")?,
            data(&self.parents, "parents")?,
            data(&self.lbs_weights, "lbs_weights")?,
            v,
            sd[2],
            j,
        )
        .map_err(py_err)
    }
}

fn inputs<'a, T: Element + Real>(
    betas: &'a Arr<'_, T>,
    pose: &'a Arr<'_, T>,
    transl: Option<&'a Arr<'_, T>>,
) -> PyResult<LbsInputs<'a, T>> {
    let batch = shape(betas, "betas", 2, "(B, NB)")?[0];
    let pb = shape(pose, "pose", 2, "(B, J·3)")?[0];
    if pb != batch {
        return Err(ShapeError::new_err(format!(
            "pose must have batch size {batch} like betas, got {pb}"
        )));
    }
    let transl = match transl {
        Some(t) => {
            shape(t, "transl", 2, "(B, 3)")?;
            Some(data(t, "transl")?)
        }
        None => None,
    };
    Ok(LbsInputs {
        betas: data(betas, "betas")?,
        pose: data(pose, "pose")?,
        transl,
        batch,
    })
}

fn forward<'py, T: Element + Real>(
    py: Python<'py>,
    betas: Arr<'py, T>,
    pose: Arr<'py, T>,
    transl: Option<Arr<'py, T>>,
    tables: Tables<'py, T>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let model = tables.model()?;
    let inputs = inputs(&betas, &pose, transl.as_ref())?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || core::lbs_forward(&model, &inputs)))
        .map_err(py_err)?;
    let (b, v, j) = (inputs.batch, model.num_verts, model.num_joints);
    PyTuple::new(
        py,
        [
            array(py, out.verts, &[b, v, 3])?,
            array(py, out.joints, &[b, j, 3])?,
            array(py, out.rotations, &[b, v, 3, 3])?,
            array(py, out.v_shaped, &[b, v, 3])?,
            array(py, out.v_posed, &[b, v, 3])?,
            array(py, out.rest_joints, &[b, j, 3])?,
        ],
    )
}

#[allow(clippy::type_complexity)]
fn backward<'py, T: Element + Real>(
    py: Python<'py>,
    betas: Arr<'py, T>,
    pose: Arr<'py, T>,
    transl: Option<Arr<'py, T>>,
    tables: Tables<'py, T>,
    saved: (Arr<'py, T>, Arr<'py, T>, Arr<'py, T>),
    grads: (Option<Arr<'py, T>>, Option<Arr<'py, T>>, Option<Arr<'py, T>>),
    needs: (bool, bool, bool, bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let model = tables.model()?;
    let inputs = inputs(&betas, &pose, transl.as_ref())?;
    let saved = LbsSaved {
        v_shaped: data(&saved.0, "v_shaped")?,
        v_posed: data(&saved.1, "v_posed")?,
        rest_joints: data(&saved.2, "rest_joints")?,
    };
    let grads_in = LbsGradOutputs {
        v_verts: optional_data(&grads.0, "v_verts")?,
        v_joints: optional_data(&grads.1, "v_joints")?,
        v_rotations: optional_data(&grads.2, "v_rotations")?,
    };
    let needs = LbsNeeds {
        betas: needs.0,
        pose: needs.1,
        transl: needs.2,
        v_template: needs.3,
        shapedirs: needs.4,
    };
    let g = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                core::lbs_backward(&model, &inputs, &saved, &grads_in, &needs)
            })
        })
        .map_err(py_err)?;
    let (b, v, nb, j) = (inputs.batch, model.num_verts, model.num_betas, model.num_joints);
    PyTuple::new(
        py,
        [
            optional(py, g.v_betas, &[b, nb])?,
            optional(py, g.v_pose, &[b, j * 3])?,
            optional(py, g.v_transl, &[b, 3])?,
            optional(py, g.v_template, &[v, 3])?,
            optional(py, g.v_shapedirs, &[v, 3, nb])?,
        ],
    )
}

/// LBS forward → (verts, joints, rotations, v_shaped, v_posed, rest_joints).
#[pyfunction]
pub fn lbs_forward<'py>(
    py: Python<'py>,
    betas: &Bound<'py, PyAny>,
    pose: &Bound<'py, PyAny>,
    transl: Option<&Bound<'py, PyAny>>,
    v_template: &Bound<'py, PyAny>,
    shapedirs: &Bound<'py, PyAny>,
    posedirs: &Bound<'py, PyAny>,
    j_regressor: &Bound<'py, PyAny>,
    parents: Arr<'py, i32>,
    lbs_weights: &Bound<'py, PyAny>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(betas, T => {
        let tables = Tables::<T> {
            v_template: v_template.extract()?,
            shapedirs: shapedirs.extract()?,
            posedirs: posedirs.extract()?,
            j_regressor: j_regressor.extract()?,
            parents,
            lbs_weights: lbs_weights.extract()?,
        };
        forward(py, betas.extract()?, pose.extract()?, optional_array(transl)?, tables, num_threads)
    })
}

/// LBS backward → (v_betas, v_pose, v_transl, v_template, v_shapedirs), None where not
/// requested.
#[pyfunction]
pub fn lbs_backward<'py>(
    py: Python<'py>,
    betas: &Bound<'py, PyAny>,
    pose: &Bound<'py, PyAny>,
    transl: Option<&Bound<'py, PyAny>>,
    v_template: &Bound<'py, PyAny>,
    shapedirs: &Bound<'py, PyAny>,
    posedirs: &Bound<'py, PyAny>,
    j_regressor: &Bound<'py, PyAny>,
    parents: Arr<'py, i32>,
    lbs_weights: &Bound<'py, PyAny>,
    v_shaped: &Bound<'py, PyAny>,
    v_posed: &Bound<'py, PyAny>,
    rest_joints: &Bound<'py, PyAny>,
    v_verts: Option<&Bound<'py, PyAny>>,
    v_joints: Option<&Bound<'py, PyAny>>,
    v_rotations: Option<&Bound<'py, PyAny>>,
    needs: (bool, bool, bool, bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(betas, T => {
        let tables = Tables::<T> {
            v_template: v_template.extract()?,
            shapedirs: shapedirs.extract()?,
            posedirs: posedirs.extract()?,
            j_regressor: j_regressor.extract()?,
            parents,
            lbs_weights: lbs_weights.extract()?,
        };
        backward(
            py,
            betas.extract()?,
            pose.extract()?,
            optional_array(transl)?,
            tables,
            (v_shaped.extract()?, v_posed.extract()?, rest_joints.extract()?),
            (optional_array(v_verts)?, optional_array(v_joints)?, optional_array(v_rotations)?),
            needs,
            num_threads,
        )
    })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(lbs_forward, m)?)?;
    m.add_function(wrap_pyfunction!(lbs_backward, m)?)?;
    Ok(())
}
