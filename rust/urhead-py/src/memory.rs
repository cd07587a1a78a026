//! Zeroed numpy arrays for large long-lived tables (UV maps, optimiser moments), from
//! `urhead_core::memory::zeroed`: fresh pages advised to be transparent huge pages before
//! their first touch, which random texel reads into a multi-hundred-MB table need (on
//! 4 KiB pages nearly every read misses the TLB). Torch's own allocator gives 4 KiB pages.

use numpy::{IntoPyArray, PyArray1};
use pyo3::prelude::*;
use urhead_core::memory::zeroed;

use crate::errors::py_err;

/// `len` float32 zeros on (advised) huge pages; MemoryError when they cannot be had.
#[pyfunction]
pub fn huge_page_zeros_f32(py: Python<'_>, len: usize) -> PyResult<Bound<'_, PyArray1<f32>>> {
    Ok(zeroed::<f32>("huge-page table", len)
        .map_err(py_err)?
        .into_pyarray(py))
}

/// `len` int32 zeros on (advised) huge pages; MemoryError when they cannot be had.
#[pyfunction]
pub fn huge_page_zeros_i32(py: Python<'_>, len: usize) -> PyResult<Bound<'_, PyArray1<i32>>> {
    Ok(zeroed::<i32>("huge-page table", len)
        .map_err(py_err)?
        .into_pyarray(py))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(huge_page_zeros_f32, m)?)?;
    m.add_function(wrap_pyfunction!(huge_page_zeros_i32, m)?)?;
    Ok(())
}
