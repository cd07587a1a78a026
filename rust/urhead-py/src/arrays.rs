//! Borrowing numpy arrays (zero-copy views of CPU torch tensors) and returning results.

use numpy::{
    Element, IntoPyArray, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyReadwriteArrayDyn,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::errors::{InvalidArgumentError, ShapeError};

/// The contiguous data of `arr`, or an error naming `arg`.
pub fn data<'a, T: Element>(arr: &'a PyReadonlyArrayDyn<'_, T>, arg: &str) -> PyResult<&'a [T]> {
    arr.as_slice().map_err(|_| {
        InvalidArgumentError::new_err(format!("{arg} must be C-contiguous; call .contiguous() first"))
    })
}

/// The contiguous data of an optional array, or an error naming `arg`.
pub fn optional_data<'a, T: Element>(
    arr: &'a Option<PyReadonlyArrayDyn<'_, T>>,
    arg: &str,
) -> PyResult<Option<&'a [T]>> {
    arr.as_ref().map(|a| data(a, arg)).transpose()
}

/// [`optional_data`] of an array checked to have `ndim` dimensions (see [`shape`]).
pub fn optional_shaped_data<'a, T: Element>(
    arr: &'a Option<PyReadonlyArrayDyn<'_, T>>,
    arg: &str,
    ndim: usize,
    layout: &str,
) -> PyResult<Option<&'a [T]>> {
    if let Some(a) = arr {
        shape(a, arg, ndim, layout)?;
    }
    optional_data(arr, arg)
}

/// The contiguous data of `arr` to write in place, or an error naming `arg`.
pub fn data_mut<'a, T: Element>(arr: &'a mut PyReadwriteArrayDyn<'_, T>, arg: &str) -> PyResult<&'a mut [T]> {
    arr.as_slice_mut().map_err(|_| {
        InvalidArgumentError::new_err(format!("{arg} must be C-contiguous; call .contiguous() first"))
    })
}

/// The shape of `arr`, checked to have `ndim` dimensions.
pub fn shape<T: Element>(
    arr: &PyReadonlyArrayDyn<'_, T>,
    arg: &str,
    ndim: usize,
    layout: &str,
) -> PyResult<Vec<usize>> {
    let s = arr.shape().to_vec();
    if s.len() != ndim {
        return Err(ShapeError::new_err(format!(
            "{arg} must be {layout}, got shape {s:?}"
        )));
    }
    Ok(s)
}

/// Moves `data` into a numpy array of shape `dims` (no copy).
pub fn array<'py, T: Element>(
    py: Python<'py>,
    data: Vec<T>,
    dims: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    data.into_pyarray(py).reshape(dims.to_vec())
}

/// An optional output: the array of shape `dims`, or None (a gradient not asked for).
pub fn optional<'py, T: Element>(py: Python<'py>, x: Option<Vec<T>>, dims: &[usize]) -> PyResult<PyObject> {
    Ok(match x {
        Some(x) => array(py, x, dims)?.into_any().unbind(),
        None => py.None(),
    })
}

/// An optional array argument of element type `T`.
pub fn optional_array<'py, T: Element>(
    arr: Option<&Bound<'py, PyAny>>,
) -> PyResult<Option<PyReadonlyArrayDyn<'py, T>>> {
    arr.map(|a| a.extract()).transpose()
}

/// Evaluates `$body` with the type alias `$t` set to the element type of the numpy array
/// `$first`, float32 or float64: one entry point serves both dtypes (its generic body is
/// instantiated for each). The other float arguments are extracted as `$t` inside `$body`;
/// Python has already checked that they share the dtype.
macro_rules! with_float_type {
    ($first:ident, $t:ident => $body:expr) => {{
        if $first.downcast::<numpy::PyArrayDyn<f32>>().is_ok() {
            type $t = f32;
            $body
        } else if $first.downcast::<numpy::PyArrayDyn<f64>>().is_ok() {
            type $t = f64;
            $body
        } else {
            Err(pyo3::exceptions::PyTypeError::new_err(concat!(
                stringify!($first),
                " must be a float32 or float64 array"
            )))
        }
    }};
}
pub(crate) use with_float_type;
