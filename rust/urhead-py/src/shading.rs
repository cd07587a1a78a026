//! Binding of `urhead_core::shading`: batched SH colour of (P, stride) coefficient rows
//! along (P, 3) view directions, forward and adjoint, float32 and float64.

use numpy::{Element, PyArrayDyn, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use urhead_core::shading::{shade_backward, shade_forward, ShadingInputs};
use urhead_core::Real;

use crate::arrays::{array, data, shape};
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
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    let (inputs, count) = inputs(&coeffs, &dirs, degree)?;
    let rgb = py
        .allow_threads(|| with_threads(num_threads, || shade_forward(&inputs)))
        .map_err(py_err)?;
    array(py, rgb, &[count, 3])
}

fn backward<'py, T: Element + Real>(
    py: Python<'py>,
    coeffs: Arr<'py, T>,
    dirs: Arr<'py, T>,
    degree: usize,
    v_rgb: Arr<'py, T>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    let (inputs, count) = inputs(&coeffs, &dirs, degree)?;
    let v = data(&v_rgb, "v_rgb")?;
    let grad = py
        .allow_threads(|| with_threads(num_threads, || shade_backward(&inputs, v)))
        .map_err(py_err)?;
    array(py, grad, &[count, inputs.stride])
}

macro_rules! entry_points {
    ($fwd:ident, $bwd:ident, $t:ty) => {
        /// (P, 3) colours of (P, stride) SH coefficient rows seen along (P, 3) directions.
        #[pyfunction]
        pub fn $fwd<'py>(
            py: Python<'py>,
            coeffs: Arr<'py, $t>,
            dirs: Arr<'py, $t>,
            degree: usize,
            num_threads: usize,
        ) -> PyResult<Bound<'py, PyArrayDyn<$t>>> {
            forward(py, coeffs, dirs, degree, num_threads)
        }

        /// (P, stride) gradient of the coefficient rows from the (P, 3) colour gradient.
        #[pyfunction]
        pub fn $bwd<'py>(
            py: Python<'py>,
            coeffs: Arr<'py, $t>,
            dirs: Arr<'py, $t>,
            degree: usize,
            v_rgb: Arr<'py, $t>,
            num_threads: usize,
        ) -> PyResult<Bound<'py, PyArrayDyn<$t>>> {
            backward(py, coeffs, dirs, degree, v_rgb, num_threads)
        }
    };
}

entry_points!(sh_shade_forward_f32, sh_shade_backward_f32, f32);
entry_points!(sh_shade_forward_f64, sh_shade_backward_f64, f64);

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(sh_shade_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(sh_shade_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(sh_shade_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(sh_shade_backward_f64, m)?)?;
    Ok(())
}
