//! Binding of `urhead_core::composite`: a premultiplied image over one behind,
//! `front + T·back`, forward and adjoint, each entry point serving float32 and float64.

use numpy::{Element, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::composite::{self as kernel, CompositeInputs};
use urhead_core::Real;

use crate::arrays::{array, data, optional, shape, with_float_type};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// The core's inputs from `front (H, W, 3)`, `transmittance (H, W)`, `back (H, W, S)`, and
/// the image's `(H, W)` and `S`.
fn inputs<'a, T: Element + Real>(
    front: &'a Arr<'_, T>,
    transmittance: &'a Arr<'_, T>,
    back: &'a Arr<'_, T>,
) -> PyResult<(CompositeInputs<'a, T>, [usize; 3])> {
    let f = shape(front, "front", 3, "(H, W, 3)")?;
    let t = shape(transmittance, "transmittance", 2, "(H, W)")?;
    let b = shape(back, "back", 3, "(H, W, S)")?;
    if f[2] != 3 || t[..] != f[..2] || b[..2] != f[..2] {
        return Err(ShapeError::new_err(format!(
            "front (H, W, 3), transmittance (H, W) and back (H, W, S) must share (H, W), got \
             {f:?}, {t:?} and {b:?}"
        )));
    }
    let inputs = CompositeInputs {
        front: data(front, "front")?,
        transmittance: data(transmittance, "transmittance")?,
        back: data(back, "back")?,
        back_channels: b[2],
    };
    Ok((inputs, [f[0], f[1], b[2]]))
}

fn forward<'py, T: Element + Real>(
    py: Python<'py>,
    front: Arr<'py, T>,
    transmittance: Arr<'py, T>,
    back: Arr<'py, T>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let (inputs, [h, w, _]) = inputs(&front, &transmittance, &back)?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || kernel::composite_forward(&inputs)))
        .map_err(py_err)?;
    Ok(array(py, out, &[h, w, 3])?.into_any())
}

fn backward<'py, T: Element + Real>(
    py: Python<'py>,
    front: Arr<'py, T>,
    transmittance: Arr<'py, T>,
    back: Arr<'py, T>,
    v_out: Arr<'py, T>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let (inputs, [h, w, s]) = inputs(&front, &transmittance, &back)?;
    let v_out = data(&v_out, "v_out")?;
    let g = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                kernel::composite_backward(&inputs, v_out, needs.0, needs.1)
            })
        })
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            optional(py, g.v_transmittance, &[h, w])?,
            optional(py, g.v_back, &[h, w, s])?,
        ],
    )
}

/// (H, W, 3) `front + transmittance·back[..., :3]`.
#[pyfunction]
pub fn composite_forward<'py>(
    py: Python<'py>,
    front: &Bound<'py, PyAny>,
    transmittance: &Bound<'py, PyAny>,
    back: &Bound<'py, PyAny>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(front, T => forward::<T>(
        py,
        front.extract()?,
        transmittance.extract()?,
        back.extract()?,
        num_threads,
    ))
}

/// (v_transmittance (H, W), v_back (H, W, S)) from the (H, W, 3) output gradient, None
/// where not requested; `needs` in that order.
#[pyfunction]
pub fn composite_backward<'py>(
    py: Python<'py>,
    front: &Bound<'py, PyAny>,
    transmittance: &Bound<'py, PyAny>,
    back: &Bound<'py, PyAny>,
    v_out: &Bound<'py, PyAny>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(front, T => backward::<T>(
        py,
        front.extract()?,
        transmittance.extract()?,
        back.extract()?,
        v_out.extract()?,
        needs,
        num_threads,
    ))
}

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(composite_forward, m)?)?;
    m.add_function(wrap_pyfunction!(composite_backward, m)?)?;
    Ok(())
}
