//! Borrowing numpy arrays (zero-copy views of CPU torch tensors) and returning results.

use numpy::{Element, IntoPyArray, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::errors::{InvalidArgumentError, ShapeError};

/// The contiguous data of `arr`, or an error naming `arg`.
pub fn data<'a, T: Element>(arr: &'a PyReadonlyArrayDyn<'_, T>, arg: &str) -> PyResult<&'a [T]> {
    arr.as_slice().map_err(|_| {
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
