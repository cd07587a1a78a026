//! Binding of `urhead_core::adam`: updates the optimiser state in place; `RowJournal`
//! crosses to Python as an opaque object the step saves rows into. Moments are float32 or
//! bfloat16 (handed over as `uint16` bits).

use numpy::{PyArrayDyn, PyReadonlyArrayDyn, PyReadwriteArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use urhead_core::adam::{
    sparse_adam_step as step, sparse_adam_step_sampled as step_sampled, AdamConfig, Bf16,
    RowJournal as CoreJournal, SparseAdamState, StepReport,
};
use urhead_core::raster::{texture_gradient_entries, TextureSamples};

use crate::arrays::{array, data, data_mut};
use crate::errors::{py_err, InvalidArgumentError};
use crate::pool::with_threads;

/// A moment table as Python hands it over: float32, or bfloat16 as its raw bits (a torch
/// `bfloat16` tensor viewed as `uint16`: numpy has no bfloat16).
#[derive(FromPyObject)]
pub enum MomentTable<'py> {
    F32(PyReadwriteArrayDyn<'py, f32>),
    Bf16(PyReadwriteArrayDyn<'py, u16>),
}

/// A core journal for either kind of moments.
enum Journal {
    F32(CoreJournal<f32>),
    Bf16(CoreJournal<Bf16>),
}

/// The values rows of one `(rows, channels)` table had before steps first changed them
/// since the last `clear()`; `restore(...)` writes them back. `moments` is the optimiser's
/// moment dtype, `"float32"` or `"bfloat16"`.
#[pyclass(module = "urhead._core")]
pub struct RowJournal {
    journal: Journal,
}

#[pymethods]
impl RowJournal {
    #[new]
    #[pyo3(signature = (rows, channels, moments="float32"))]
    fn new(rows: usize, channels: usize, moments: &str) -> PyResult<Self> {
        let journal = match moments {
            "float32" => Journal::F32(CoreJournal::new(rows, channels)),
            "bfloat16" => Journal::Bf16(CoreJournal::new(rows, channels)),
            other => {
                return Err(InvalidArgumentError::new_err(format!(
                    "moments must be \"float32\" or \"bfloat16\", got {other:?}"
                )))
            }
        };
        Ok(Self { journal })
    }

    fn __len__(&self) -> usize {
        match &self.journal {
            Journal::F32(j) => j.len(),
            Journal::Bf16(j) => j.len(),
        }
    }

    fn clear(&mut self) {
        match &mut self.journal {
            Journal::F32(j) => j.clear(),
            Journal::Bf16(j) => j.clear(),
        }
    }

    /// Writes the saved rows back into the `(N, C)` tables and `(N,)` step counts.
    fn restore(
        &mut self,
        mut param: PyReadwriteArrayDyn<'_, f32>,
        mut exp_avg: MomentTable<'_>,
        mut exp_avg_sq: MomentTable<'_>,
        mut steps: PyReadwriteArrayDyn<'_, i32>,
    ) -> PyResult<()> {
        let channels = param.shape().last().copied().unwrap_or(0);
        let state = adam_state(
            &mut param,
            &mut exp_avg,
            &mut exp_avg_sq,
            &mut steps,
            channels,
            Some(self),
        )?;
        match state {
            Typed::F32(mut state, Some(j)) => j.restore(&mut state),
            Typed::Bf16(mut state, Some(j)) => j.restore(&mut state),
            _ => unreachable!("a journal was given"),
        }
        .map_err(py_err)
    }
}

/// The optimiser's tables as the core's state, its moments of either kind, with the
/// journal (if any) of the same kind.
enum Typed<'a> {
    F32(SparseAdamState<'a, f32>, Option<&'a mut CoreJournal<f32>>),
    Bf16(SparseAdamState<'a, Bf16>, Option<&'a mut CoreJournal<Bf16>>),
}

/// The optimiser's tables as the core's state with `channels` per row, paired with
/// `journal`, which must keep the same kind of moments.
fn adam_state<'a>(
    param: &'a mut PyReadwriteArrayDyn<'_, f32>,
    exp_avg: &'a mut MomentTable<'_>,
    exp_avg_sq: &'a mut MomentTable<'_>,
    steps: &'a mut PyReadwriteArrayDyn<'_, i32>,
    channels: usize,
    journal: Option<&'a mut RowJournal>,
) -> PyResult<Typed<'a>> {
    let (param, steps) = (data_mut(param, "param")?, data_mut(steps, "steps")?);
    let journal = journal.map(|j| &mut j.journal);
    let other_kind = |kind: &str| {
        InvalidArgumentError::new_err(format!(
            "journal keeps moments of the other kind than the {kind} moments given"
        ))
    };
    match (exp_avg, exp_avg_sq) {
        (MomentTable::F32(m), MomentTable::F32(v)) => {
            let journal = match journal {
                None => None,
                Some(Journal::F32(j)) => Some(j),
                Some(Journal::Bf16(_)) => return Err(other_kind("float32")),
            };
            let state = SparseAdamState {
                param,
                exp_avg: data_mut(m, "exp_avg")?,
                exp_avg_sq: data_mut(v, "exp_avg_sq")?,
                steps,
                channels,
            };
            Ok(Typed::F32(state, journal))
        }
        (MomentTable::Bf16(m), MomentTable::Bf16(v)) => {
            let journal = match journal {
                None => None,
                Some(Journal::Bf16(j)) => Some(j),
                Some(Journal::F32(_)) => return Err(other_kind("bfloat16")),
            };
            let state = SparseAdamState {
                param,
                exp_avg: Bf16::from_bits_mut(data_mut(m, "exp_avg")?),
                exp_avg_sq: Bf16::from_bits_mut(data_mut(v, "exp_avg_sq")?),
                steps,
                channels,
            };
            Ok(Typed::Bf16(state, journal))
        }
        _ => Err(InvalidArgumentError::new_err(
            "exp_avg and exp_avg_sq must both be float32 or both bfloat16 (as uint16)",
        )),
    }
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
    mut exp_avg: MomentTable<'_>,
    mut exp_avg_sq: MomentTable<'_>,
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
    let typed = adam_state(
        &mut param,
        &mut exp_avg,
        &mut exp_avg_sq,
        &mut steps,
        channels,
        journal.as_deref_mut(),
    )?;
    let (rows, grads) = (data(&rows, "rows")?, data(&grads, "grads")?);
    let settings = Settings::new(&lr, beta1, beta2, eps, num_threads)?;
    settings.run(py, channels, |lr, config| match typed {
        Typed::F32(mut s, j) => step(&mut s, rows, grads, lr, config, j),
        Typed::Bf16(mut s, j) => step(&mut s, rows, grads, lr, config, j),
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
    mut exp_avg: MomentTable<'_>,
    mut exp_avg_sq: MomentTable<'_>,
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
    let typed = adam_state(
        &mut param,
        &mut exp_avg,
        &mut exp_avg_sq,
        &mut steps,
        channels,
        journal.as_deref_mut(),
    )?;
    let segments = segments
        .iter()
        .map(|(uv, v_out)| {
            Ok(TextureSamples {
                uv: data(uv, "uv")?,
                v_out: data(v_out, "v_out")?,
            })
        })
        .collect::<PyResult<Vec<_>>>()?;
    let settings = Settings::new(&lr, beta1, beta2, eps, num_threads)?;
    settings.run(py, channels, |lr, config| {
        let texels = texture_gradient_entries(height, width, channels, &segments)?;
        match typed {
            Typed::F32(mut s, j) => step_sampled(&mut s, &texels, lr, config, j),
            Typed::Bf16(mut s, j) => step_sampled(&mut s, &texels, lr, config, j),
        }
    })
}

/// What both steps take besides the tables and the gradient.
struct Settings<'a> {
    lr: &'a [f32],
    config: AdamConfig,
    num_threads: usize,
}

impl<'a> Settings<'a> {
    fn new(
        lr: &'a PyReadonlyArrayDyn<'_, f32>,
        beta1: f64,
        beta2: f64,
        eps: f64,
        num_threads: usize,
    ) -> PyResult<Self> {
        Ok(Self {
            lr: data(lr, "lr")?,
            config: AdamConfig { beta1, beta2, eps },
            num_threads,
        })
    }

    /// Runs `step` without the GIL on the step's threads; returns its report as
    /// `(rejected_rows, non_finite_rows, peaks (C,))`.
    fn run<'py>(
        self,
        py: Python<'py>,
        channels: usize,
        step: impl FnOnce(&[f32], &AdamConfig) -> urhead_core::Result<StepReport> + Send,
    ) -> PyResult<(usize, usize, Bound<'py, PyArrayDyn<f32>>)> {
        let Self {
            lr,
            config,
            num_threads,
        } = self;
        let report = py
            .allow_threads(|| with_threads(num_threads, || step(lr, &config)))
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
