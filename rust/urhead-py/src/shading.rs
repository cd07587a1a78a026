//! Binding of `urhead_core::shading`: batched SH colour of (P, stride) coefficient rows
//! along (P, 3) view directions, forward and adjoint, each entry point serving float32 and float64.

use numpy::{Element, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use urhead_core::shading::{shade_backward, shade_forward, RestGradient, ShadingInputs};
use urhead_core::Real;

use crate::arrays::{array, data, shape, with_float_type};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

fn inputs<'a, T: Element + Real>(
    coeffs: &'a Arr<'_, T>,
    dirs: &'a Arr<'_, T>,
    degree: usize,
) -> PyResult<(ShadingInputs<'a, T>, usize)> {
    let c = shape(coeffs, "coeffs", 2, "(P, stride)")?;
    let d = shape(dirs, "dirs", 2, "(P, 3)")?;
    if d[1] != 3 || d[0] != c[0] {
        return Err(ShapeError::new_err(format!(
            "dirs must be (P, 3) with P = {} like coeffs, got {d:?}",
            c[0]
        )));
    }
    let inputs = ShadingInputs {
        coeffs: data(coeffs, "coeffs")?,
        dirs: data(dirs, "dirs")?,
        stride: c[1],
        degree,
    };
    Ok((inputs, c[0]))
}

fn forward<'py, T: Element + Real>(
    py: Python<'py>,
    coeffs: Arr<'py, T>,
    dirs: Arr<'py, T>,
    degree: usize,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let (inputs, count) = inputs(&coeffs, &dirs, degree)?;
    let rgb = py
        .allow_threads(|| with_threads(num_threads, || shade_forward(&inputs)))
        .map_err(py_err)?;
    Ok(array(py, rgb, &[count, 3])?.into_any())
}

fn backward<'py, T: Element + Real>(
    py: Python<'py>,
    coeffs: Arr<'py, T>,
    dirs: Arr<'py, T>,
    degree: usize,
    v_rgb: Arr<'py, T>,
    rest: Option<(Arr<'py, T>, usize)>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let (inputs, count) = inputs(&coeffs, &dirs, degree)?;
    let v = data(&v_rgb, "v_rgb")?;
    let rest = match &rest {
        None => None,
        Some((values, start)) => Some(RestGradient {
            width: shape(values, "rest", 2, "(P, width)")?[1],
            values: data(values, "rest")?,
            start: *start,
        }),
    };
    let grad = py
        .allow_threads(|| with_threads(num_threads, || shade_backward(&inputs, v, rest)))
        .map_err(py_err)?;
    Ok(array(py, grad, &[count, inputs.stride])?.into_any())
}

/// (P, 3) colours of (P, stride) SH coefficient rows seen along (P, 3) directions.
#[pyfunction]
pub fn sh_shade_forward<'py>(
    py: Python<'py>,
    coeffs: &Bound<'py, PyAny>,
    dirs: &Bound<'py, PyAny>,
    degree: usize,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(coeffs, T => forward::<T>(
        py,
        coeffs.extract()?,
        dirs.extract()?,
        degree,
        num_threads,
    ))
}

/// (P, stride) gradient of the coefficient rows from the (P, 3) colour gradient; with
/// `rest = (values (P, width), start)` the other channels' gradient written at channels
/// `start..start + width` in the same pass.
#[pyfunction]
#[pyo3(signature = (coeffs, dirs, degree, v_rgb, rest, num_threads))]
pub fn sh_shade_backward<'py>(
    py: Python<'py>,
    coeffs: &Bound<'py, PyAny>,
    dirs: &Bound<'py, PyAny>,
    degree: usize,
    v_rgb: &Bound<'py, PyAny>,
    rest: Option<(Bound<'py, PyAny>, usize)>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(coeffs, T => backward::<T>(
        py,
        coeffs.extract()?,
        dirs.extract()?,
        degree,
        v_rgb.extract()?,
        rest.map(|(values, start)| values.extract().map(|v| (v, start))).transpose()?,
        num_threads,
    ))
}

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(sh_shade_forward, m)?)?;
    m.add_function(wrap_pyfunction!(sh_shade_backward, m)?)?;
    Ok(())
}
