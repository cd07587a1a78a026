//! Binding of `urhead_core::lift` and `lift_tail`: the Gaussian lift's forward and adjoint,
//! and its maps split out of the map rows (and their gradients joined back), each entry
//! point serving float32 and float64 through one generic body.

use numpy::{Element, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::lift::{lift_backward, lift_forward, LiftGradOutputs, LiftInputs, LiftNeeds};
use urhead_core::lift_tail::{join_tail_grad, split_tail, TailGrads, TailLayout};
use urhead_core::Real;

use crate::arrays::{array, data, optional, optional_array, optional_data, with_float_type};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// Checks the number of dimensions and every trailing size given (`None`: any); returns
/// the leading size.
fn leading<T: Element>(arr: &Arr<'_, T>, arg: &str, trailing: &[usize], layout: &str) -> PyResult<usize> {
    let s = arr.shape();
    if s.len() != trailing.len() + 1 || s[1..] != *trailing {
        return Err(ShapeError::new_err(format!(
            "{arg} must be {layout}, got shape {s:?}"
        )));
    }
    Ok(s[0])
}

/// The borrowed inputs of both passes.
struct Arrays<'py, T: Element> {
    verts: Arr<'py, T>,
    rotations: Arr<'py, T>,
    face_verts: Arr<'py, i32>,
    bary: Arr<'py, T>,
    normals: Arr<'py, T>,
    lift: Arr<'py, T>,
    centre: Arr<'py, T>,
}

impl<'py, T: Element + Real> Arrays<'py, T> {
    fn extract(
        verts: &Bound<'py, PyAny>,
        rotations: &Bound<'py, PyAny>,
        face_verts: Arr<'py, i32>,
        bary: &Bound<'py, PyAny>,
        normals: &Bound<'py, PyAny>,
        lift: &Bound<'py, PyAny>,
        centre: &Bound<'py, PyAny>,
    ) -> PyResult<Self> {
        Ok(Self {
            verts: verts.extract()?,
            rotations: rotations.extract()?,
            face_verts,
            bary: bary.extract()?,
            normals: normals.extract()?,
            lift: lift.extract()?,
            centre: centre.extract()?,
        })
    }

    /// The core's inputs and `(N, V)`.
    fn inputs(&self) -> PyResult<(LiftInputs<'_, T>, usize, usize)> {
        let v = leading(&self.verts, "verts", &[3], "(V, 3)")?;
        leading(&self.rotations, "rotations", &[3, 3], "(V, 3, 3)")?;
        let n = leading(&self.face_verts, "face_verts", &[3], "(N, 3) int32")?;
        leading(&self.bary, "bary", &[3], "(N, 3)")?;
        leading(&self.normals, "normals", &[3], "(N, 3)")?;
        leading(&self.lift, "lift", &[], "(N,)")?;
        leading(&self.centre, "centre", &[], "(3,)")?;
        let inputs = LiftInputs {
            verts: data(&self.verts, "verts")?,
            rotations: data(&self.rotations, "rotations")?,
            face_verts: data(&self.face_verts, "face_verts")?,
            bary: data(&self.bary, "bary")?,
            normals: data(&self.normals, "normals")?,
            lift: data(&self.lift, "lift")?,
            centre: data(&self.centre, "centre")?,
        };
        Ok((inputs, n, v))
    }
}

fn forward<'py, T: Element + Real>(
    py: Python<'py>,
    arrays: Arrays<'py, T>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let (inputs, n, _) = arrays.inputs()?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || lift_forward(&inputs)))
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            array(py, out.means, &[n, 3])?,
            array(py, out.normals, &[n, 3])?,
            array(py, out.quats, &[n, 4])?,
            array(py, out.frames, &[n, 3, 3])?,
            array(py, out.view_dirs, &[n, 3])?,
        ],
    )
}

fn backward<'py, T: Element + Real>(
    py: Python<'py>,
    arrays: Arrays<'py, T>,
    grads: [Option<Arr<'py, T>>; 3],
    needs: (bool, bool, bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let (inputs, n, v) = arrays.inputs()?;
    let [v_means, v_normals, v_quats] = &grads;
    let grads_in = LiftGradOutputs {
        v_means: optional_data(v_means, "v_means")?,
        v_normals: optional_data(v_normals, "v_normals")?,
        v_quats: optional_data(v_quats, "v_quats")?,
    };
    let needs = LiftNeeds {
        verts: needs.0,
        rotations: needs.1,
        normals: needs.2,
        lift: needs.3,
    };
    let g = py
        .allow_threads(|| with_threads(num_threads, || lift_backward(&inputs, &grads_in, &needs)))
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            optional(py, g.v_verts, &[v, 3])?,
            optional(py, g.v_rotations, &[v, 3, 3])?,
            optional(py, g.v_normals, &[n, 3])?,
            optional(py, g.v_lift, &[n])?,
        ],
    )
}

/// Gaussian lift forward → (means (N, 3), normals (N, 3), quats (N, 4), frames (N, 3, 3),
/// view_dirs (N, 3)).
#[pyfunction]
pub fn lift_gaussians_forward<'py>(
    py: Python<'py>,
    verts: &Bound<'py, PyAny>,
    rotations: &Bound<'py, PyAny>,
    face_verts: Arr<'py, i32>,
    bary: &Bound<'py, PyAny>,
    normals: &Bound<'py, PyAny>,
    lift: &Bound<'py, PyAny>,
    centre: &Bound<'py, PyAny>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(verts, T => {
        let arrays = Arrays::<T>::extract(verts, rotations, face_verts, bary, normals, lift, centre)?;
        forward(py, arrays, num_threads)
    })
}

/// Gaussian lift backward → (v_verts, v_rotations, v_normals, v_lift), None where not
/// requested; `needs` in that order.
#[pyfunction]
pub fn lift_gaussians_backward<'py>(
    py: Python<'py>,
    verts: &Bound<'py, PyAny>,
    rotations: &Bound<'py, PyAny>,
    face_verts: Arr<'py, i32>,
    bary: &Bound<'py, PyAny>,
    normals: &Bound<'py, PyAny>,
    lift: &Bound<'py, PyAny>,
    centre: &Bound<'py, PyAny>,
    v_means: Option<&Bound<'py, PyAny>>,
    v_normals: Option<&Bound<'py, PyAny>>,
    v_quats: Option<&Bound<'py, PyAny>>,
    needs: (bool, bool, bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(verts, T => {
        let arrays = Arrays::<T>::extract(verts, rotations, face_verts, bary, normals, lift, centre)?;
        let grads = [optional_array(v_means)?, optional_array(v_normals)?, optional_array(v_quats)?];
        backward(py, arrays, grads, needs, num_threads)
    })
}

/// The lift's maps split out of the Gaussians' map rows `(N, C)`, whose tail starts at
/// channel `start` → (normals (N, 3), lift (N,), raw scales (N, 3), raw opacities (N,),
/// offset (N,) or None); `offset` the offset map's channel in the tail.
#[pyfunction]
pub fn lift_tail_split<'py>(
    py: Python<'py>,
    rows: &Bound<'py, PyAny>,
    start: usize,
    offset: Option<usize>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(rows, T => {
        let rows: Arr<'py, T> = rows.extract()?;
        let n = leading(&rows, "rows", &[rows.shape().get(1).copied().unwrap_or(0)], "(N, C)")?;
        let layout = TailLayout { channels: rows.shape()[1], start, offset };
        let data = data(&rows, "rows")?;
        let out = py
            .allow_threads(|| with_threads(num_threads, || split_tail(data, &layout)))
            .map_err(py_err)?;
        PyTuple::new(
            py,
            [
                array(py, out.normals, &[n, 3])?.into_any().unbind(),
                array(py, out.lift, &[n])?.into_any().unbind(),
                array(py, out.scales, &[n, 3])?.into_any().unbind(),
                array(py, out.opacities, &[n])?.into_any().unbind(),
                optional(py, out.offset, &[n])?,
            ],
        )
    })
}

/// The tail's gradient `(N, C − start)` from the lift maps' gradients (each None when
/// none came back): `v_normals` with `v_lift`, `v_scales` (of `exp(S)`, whose values are
/// `scales`), `v_opacities` (of `sigmoid(O)`: `opacities`), `v_offset` (E's own).
#[pyfunction]
pub fn lift_tail_grad<'py>(
    py: Python<'py>,
    scales: &Bound<'py, PyAny>,
    opacities: &Bound<'py, PyAny>,
    channels: usize,
    start: usize,
    offset: Option<usize>,
    v_normals: Option<&Bound<'py, PyAny>>,
    v_lift: Option<&Bound<'py, PyAny>>,
    v_scales: Option<&Bound<'py, PyAny>>,
    v_opacities: Option<&Bound<'py, PyAny>>,
    v_offset: Option<&Bound<'py, PyAny>>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(scales, T => {
        let scales: Arr<'py, T> = scales.extract()?;
        let opacities: Arr<'py, T> = opacities.extract()?;
        let n = leading(&scales, "scales", &[3], "(N, 3)")?;
        leading(&opacities, "opacities", &[], "(N,)")?;
        let [v_normals, v_lift, v_scales, v_opacities, v_offset] = [
            optional_array::<T>(v_normals)?,
            optional_array::<T>(v_lift)?,
            optional_array::<T>(v_scales)?,
            optional_array::<T>(v_opacities)?,
            optional_array::<T>(v_offset)?,
        ];
        let normals_and_lift = match (optional_data(&v_normals, "v_normals")?, optional_data(&v_lift, "v_lift")?) {
            (Some(n), Some(l)) => Some((n, l)),
            (None, None) => None,
            _ => {
                return Err(ShapeError::new_err("v_normals and v_lift come together or not at all"));
            }
        };
        let grads = TailGrads {
            normals_and_lift,
            scales: optional_data(&v_scales, "v_scales")?.map(|v| Ok::<_, PyErr>((v, data(&scales, "scales")?))).transpose()?,
            opacities: optional_data(&v_opacities, "v_opacities")?
                .map(|v| Ok::<_, PyErr>((v, data(&opacities, "opacities")?)))
                .transpose()?,
            offset: optional_data(&v_offset, "v_offset")?,
        };
        let layout = TailLayout { channels, start, offset };
        let out = py
            .allow_threads(|| with_threads(num_threads, || join_tail_grad(n, &layout, &grads)))
            .map_err(py_err)?;
        Ok(array(py, out, &[n, channels.saturating_sub(start)])?.into_any())
    })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(lift_gaussians_forward, m)?)?;
    m.add_function(wrap_pyfunction!(lift_gaussians_backward, m)?)?;
    m.add_function(wrap_pyfunction!(lift_tail_split, m)?)?;
    m.add_function(wrap_pyfunction!(lift_tail_grad, m)?)?;
    Ok(())
}
