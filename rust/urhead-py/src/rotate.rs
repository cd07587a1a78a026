//! Binding of `urhead_core::rotate`: unit `R·v` (or `Rᵀ·v`) of (N, 3, 3) matrices and (N, 3)
//! vectors (or rows picked from an (M, 3) table), forward and adjoint, each entry point
//! serving float32 and float64.

use numpy::{Element, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::rotate::{self as kernel, RotateInputs, RotateNeeds};
use urhead_core::Real;

use crate::arrays::{array, data, optional, optional_data, shape, with_float_type};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// The core's inputs and N; the core checks that the row counts agree and the rows.
fn inputs<'a, T: Element + Real>(
    rotations: &'a Arr<'_, T>,
    vectors: &'a Arr<'_, T>,
    transpose: bool,
    rows: &'a Option<Arr<'_, i64>>,
) -> PyResult<(RotateInputs<'a, T>, usize)> {
    let r = shape(rotations, "rotations", 3, "(N, 3, 3)")?;
    if r[1..] != [3, 3] {
        return Err(ShapeError::new_err(format!(
            "rotations must be (N, 3, 3), got shape {r:?}"
        )));
    }
    match rows {
        None => shape(vectors, "vectors", 2, "(N, 3)")?,
        Some(rows) => {
            shape(rows, "rows", 1, "(N,) int64")?;
            shape(vectors, "vectors", 2, "(M, 3)")?
        }
    };
    let inputs = RotateInputs {
        rotations: data(rotations, "rotations")?,
        vectors: data(vectors, "vectors")?,
        transpose,
        rows: optional_data(rows, "rows")?,
    };
    Ok((inputs, r[0]))
}

fn forward<'py, T: Element + Real>(
    py: Python<'py>,
    rotations: Arr<'py, T>,
    vectors: Arr<'py, T>,
    transpose: bool,
    rows: Option<Arr<'py, i64>>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let (inputs, n) = inputs(&rotations, &vectors, transpose, &rows)?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || kernel::rotate_normalize_forward(&inputs)))
        .map_err(py_err)?;
    Ok(array(py, out, &[n, 3])?.into_any())
}

fn backward<'py, T: Element + Real>(
    py: Python<'py>,
    rotations: Arr<'py, T>,
    vectors: Arr<'py, T>,
    transpose: bool,
    rows: Option<Arr<'py, i64>>,
    v_out: Arr<'py, T>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let (inputs, n) = inputs(&rotations, &vectors, transpose, &rows)?;
    let v_out = data(&v_out, "v_out")?;
    let needs = RotateNeeds {
        rotations: needs.0,
        vectors: needs.1,
    };
    let g = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                kernel::rotate_normalize_backward(&inputs, v_out, &needs)
            })
        })
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            optional(py, g.v_rotations, &[n, 3, 3])?,
            optional(py, g.v_vectors, &[n, 3])?,
        ],
    )
}

/// (N, 3) unit `R·v` (`Rᵀ·v` with `transpose`) of (N, 3, 3) matrices and (N, 3) vectors,
/// or the (M, 3) table's `rows` (N,) int64 when not None.
#[pyfunction]
#[pyo3(signature = (rotations, vectors, transpose, rows, num_threads))]
pub fn rotate_normalize_forward<'py>(
    py: Python<'py>,
    rotations: &Bound<'py, PyAny>,
    vectors: &Bound<'py, PyAny>,
    transpose: bool,
    rows: Option<Arr<'py, i64>>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(rotations, T => forward::<T>(
        py,
        rotations.extract()?,
        vectors.extract()?,
        transpose,
        rows,
        num_threads,
    ))
}

/// (v_rotations (N, 3, 3), v_vectors (N, 3)) from the (N, 3) output gradient, None where
/// not requested; `needs` in that order (no vector gradient with `rows`).
#[pyfunction]
#[pyo3(signature = (rotations, vectors, transpose, rows, v_out, needs, num_threads))]
pub fn rotate_normalize_backward<'py>(
    py: Python<'py>,
    rotations: &Bound<'py, PyAny>,
    vectors: &Bound<'py, PyAny>,
    transpose: bool,
    rows: Option<Arr<'py, i64>>,
    v_out: &Bound<'py, PyAny>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(rotations, T => backward::<T>(
        py,
        rotations.extract()?,
        vectors.extract()?,
        transpose,
        rows,
        v_out.extract()?,
        needs,
        num_threads,
    ))
}

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(rotate_normalize_forward, m)?)?;
    m.add_function(wrap_pyfunction!(rotate_normalize_backward, m)?)?;
    Ok(())
}
