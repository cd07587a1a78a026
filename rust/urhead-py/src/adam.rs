//! Binding of `urhead_core::adam`: updates the optimiser state in place; `RowJournal`
//! crosses to Python as an opaque object the step saves rows into.

use numpy::{PyArrayDyn, PyReadonlyArrayDyn, PyReadwriteArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use urhead_core::adam::{
    sparse_adam_step as step, sparse_adam_step_sampled as step_sampled, AdamConfig,
    RowJournal as CoreJournal, SparseAdamState, StepReport,
};
use urhead_core::raster::{texture_gradient_entries, TextureSamples};

use crate::arrays::{array, data, data_mut};
use crate::errors::{py_err, InvalidArgumentError};
use crate::pool::with_threads;

/// The values rows of one `(rows, channels)` table had before steps first changed them
/// since the last `clear()`; `restore(...)` writes them back.
#[pyclass(module = "urhead._core")]
pub struct RowJournal {
    journal: CoreJournal,
}

#[pymethods]
impl RowJournal {
    #[new]
    fn new(rows: usize, channels: usize) -> Self {
        Self {
            journal: CoreJournal::new(rows, channels),
        }
    }

    fn __len__(&self) -> usize {
        self.journal.len()
    }

    fn clear(&mut self) {
        self.journal.clear();
    }

    /// Writes the saved rows back into the `(N, C)` tables and `(N,)` step counts.
    fn restore(
        &self,
        mut param: PyReadwriteArrayDyn<'_, f32>,
        mut exp_avg: PyReadwriteArrayDyn<'_, f32>,
        mut exp_avg_sq: PyReadwriteArrayDyn<'_, f32>,
        mut steps: PyReadwriteArrayDyn<'_, i32>,
    ) -> PyResult<()> {
        let channels = param.shape().last().copied().unwrap_or(0);
        let mut state = adam_state(&mut param, &mut exp_avg, &mut exp_avg_sq, &mut steps, channels)?;
        self.journal.restore(&mut state).map_err(py_err)
    }
}

/// The optimiser's tables as the core's [`SparseAdamState`] with `channels` per row.
fn adam_state<'a>(
    param: &'a mut PyReadwriteArrayDyn<'_, f32>,
    exp_avg: &'a mut PyReadwriteArrayDyn<'_, f32>,
    exp_avg_sq: &'a mut PyReadwriteArrayDyn<'_, f32>,
    steps: &'a mut PyReadwriteArrayDyn<'_, i32>,
    channels: usize,
) -> PyResult<SparseAdamState<'a>> {
    Ok(SparseAdamState {
        param: data_mut(param, "param")?,
        exp_avg: data_mut(exp_avg, "exp_avg")?,
        exp_avg_sq: data_mut(exp_avg_sq, "exp_avg_sq")?,
        steps: data_mut(steps, "steps")?,
        channels,
    })
}

/// One sparse Adam step over `rows` of the `(N, C)` tables, saving rows into `journal`
/// first when given. Returns `(rejected_rows, non_finite_rows, peaks (C,))`: rows skipped
/// for a non-finite gradient, rows whose update came out non-finite, and each channel's
/// largest gradient magnitude (+inf where an entry was non-finite).
#[pyfunction]
#[pyo3(signature = (param, exp_avg, exp_avg_sq, steps, rows, grads, lr, beta1, beta2, eps, num_threads, journal=None))]
#[allow(clippy::too_many_arguments)]
pub fn sparse_adam_step<'py>(
    py: Python<'py>,
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
    mut journal: Option<PyRefMut<'_, RowJournal>>,
) -> PyResult<(usize, usize, Bound<'py, PyArrayDyn<f32>>)> {
    let channels = lr.len();
    let mut state = adam_state(&mut param, &mut exp_avg, &mut exp_avg_sq, &mut steps, channels)?;
    let (rows, grads) = (data(&rows, "rows")?, data(&grads, "grads")?);
    let settings = Settings::new(&lr, beta1, beta2, eps, num_threads, journal.as_deref_mut())?;
    settings.run(py, channels, |lr, config, journal| {
        step(&mut state, rows, grads, lr, config, journal)
    })
}

/// [`sparse_adam_step`] of a texture table `param (Ht, Wt, C)` whose gradient is that of
/// bilinear lookups given as `segments`, a list of `(uv (N_i, 2), v_out (N_i, C))` (each
/// lookup's own arrays, taken in order as if concatenated): built and applied in one pass,
/// never stored. The same result, bit for bit, as the step on the coalesced gradient
/// `texture_backward` gives for the concatenated lookups.
#[pyfunction]
#[pyo3(signature = (param, exp_avg, exp_avg_sq, steps, segments, lr, beta1, beta2, eps, num_threads, journal=None))]
#[allow(clippy::too_many_arguments)]
pub fn sparse_adam_step_sampled<'py>(
    py: Python<'py>,
    mut param: PyReadwriteArrayDyn<'_, f32>,
    mut exp_avg: PyReadwriteArrayDyn<'_, f32>,
    mut exp_avg_sq: PyReadwriteArrayDyn<'_, f32>,
    mut steps: PyReadwriteArrayDyn<'_, i32>,
    segments: Vec<(PyReadonlyArrayDyn<'_, f32>, PyReadonlyArrayDyn<'_, f32>)>,
    lr: PyReadonlyArrayDyn<'_, f32>,
    beta1: f64,
    beta2: f64,
    eps: f64,
    num_threads: usize,
    mut journal: Option<PyRefMut<'_, RowJournal>>,
) -> PyResult<(usize, usize, Bound<'py, PyArrayDyn<f32>>)> {
    let &[height, width, channels] = param.shape() else {
        return Err(InvalidArgumentError::new_err(format!(
            "param must be a texture (Ht, Wt, C), got shape {:?}",
            param.shape()
        )));
    };
    let mut state = adam_state(&mut param, &mut exp_avg, &mut exp_avg_sq, &mut steps, channels)?;
    let segments = segments
        .iter()
        .map(|(uv, v_out)| {
            Ok(TextureSamples {
                uv: data(uv, "uv")?,
                v_out: data(v_out, "v_out")?,
            })
        })
        .collect::<PyResult<Vec<_>>>()?;
    let settings = Settings::new(&lr, beta1, beta2, eps, num_threads, journal.as_deref_mut())?;
    settings.run(py, channels, |lr, config, journal| {
        let texels = texture_gradient_entries(height, width, channels, &segments)?;
        step_sampled(&mut state, &texels, lr, config, journal)
    })
}

/// What both steps take besides the tables and the gradient.
struct Settings<'a> {
    lr: &'a [f32],
    config: AdamConfig,
    num_threads: usize,
    journal: Option<&'a mut CoreJournal>,
}

impl<'a> Settings<'a> {
    fn new(
        lr: &'a PyReadonlyArrayDyn<'_, f32>,
        beta1: f64,
        beta2: f64,
        eps: f64,
        num_threads: usize,
        journal: Option<&'a mut RowJournal>,
    ) -> PyResult<Self> {
        Ok(Self {
            lr: data(lr, "lr")?,
            config: AdamConfig { beta1, beta2, eps },
            num_threads,
            journal: journal.map(|j| &mut j.journal),
        })
    }

    /// Runs `step` without the GIL on the step's threads; returns its report as
    /// `(rejected_rows, non_finite_rows, peaks (C,))`.
    fn run<'py>(
        self,
        py: Python<'py>,
        channels: usize,
        step: impl FnOnce(&[f32], &AdamConfig, Option<&mut CoreJournal>) -> urhead_core::Result<StepReport> + Send,
    ) -> PyResult<(usize, usize, Bound<'py, PyArrayDyn<f32>>)> {
        let Self {
            lr,
            config,
            num_threads,
            journal,
        } = self;
        let report = py
            .allow_threads(|| with_threads(num_threads, || step(lr, &config, journal)))
            .map_err(py_err)?;
        let peaks = array(py, report.peaks, &[channels])?;
        Ok((report.rejected_rows, report.non_finite_rows, peaks))
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(sparse_adam_step, m)?)?;
    m.add_function(wrap_pyfunction!(sparse_adam_step_sampled, m)?)?;
    m.add_class::<RowJournal>()?;
    Ok(())
}
