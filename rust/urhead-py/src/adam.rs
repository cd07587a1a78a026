//! Binding of `urhead_core::adam`: updates the optimiser state in place.

use numpy::{PyReadonlyArrayDyn, PyReadwriteArrayDyn};
use pyo3::prelude::*;
use urhead_core::adam::{sparse_adam_step as step, AdamConfig, SparseAdamState};

use crate::arrays::data;
use crate::errors::{py_err, InvalidArgumentError};
use crate::pool::with_threads;

fn data_mut<'a, T: numpy::Element>(
    arr: &'a mut PyReadwriteArrayDyn<'_, T>,
    arg: &str,
) -> PyResult<&'a mut [T]> {
    arr.as_slice_mut().map_err(|_| {
        InvalidArgumentError::new_err(format!("{arg} must be C-contiguous; call .contiguous() first"))
    })
}

/// One sparse Adam step over `rows` of the `(N, C)` tables; returns the number of rows
/// rejected for non-finite gradients.
#[pyfunction]
pub fn sparse_adam_step(
    py: Python<'_>,
    mut param: PyReadwriteArrayDyn<'_, f32>,
    mut exp_avg: PyReadwriteArrayDyn<'_, f32>,
    mut exp_avg_sq: PyReadwriteArrayDyn<'_, f32>,
    mut steps: PyReadwriteArrayDyn<'_, i32>,
    rows: PyReadonlyArrayDyn<'_, i64>,
    grads: PyReadonlyArrayDyn<'_, f32>,
    lr: PyReadonlyArrayDyn<'_, f32>,
    beta1: f64,
    beta2: f64,
    eps: f64,
    num_threads: usize,
) -> PyResult<usize> {
    let channels = lr.len()?;
    let mut state = SparseAdamState {
        param: data_mut(&mut param, "param")?,
        exp_avg: data_mut(&mut exp_avg, "exp_avg")?,
        exp_avg_sq: data_mut(&mut exp_avg_sq, "exp_avg_sq")?,
        steps: data_mut(&mut steps, "steps")?,
        channels,
    };
    let (rows, grads, lr) = (data(&rows, "rows")?, data(&grads, "grads")?, data(&lr, "lr")?);
    let config = AdamConfig { beta1, beta2, eps };
    py.allow_threads(|| with_threads(num_threads, || step(&mut state, rows, grads, lr, &config)))
        .map_err(py_err)
}
