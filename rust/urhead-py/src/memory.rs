//! Zeroed numpy arrays for large long-lived tables (UV maps, optimiser moments), from
//! `urhead_core::memory::zeroed_resident`: fresh pages advised to be transparent huge
//! pages before their first touch (a write), which random texel reads into a multi-hundred-MB table need (on
//! 4 KiB pages nearly every read misses the TLB). Torch's own allocator gives 4 KiB pages.

use numpy::IntoPyArray;
use pyo3::prelude::*;
use urhead_core::memory::zeroed_resident;

use crate::errors::{py_err, InvalidArgumentError};

const WHAT: &str = "huge-page table";

/// `len` zeros of numpy dtype `dtype` ("float32", "int32", or "uint16" for the bits of
/// bfloat16, which numpy lacks) on (advised) huge pages, made resident by a first write
/// (`zeroed_resident`: a moment read before it is written keeps its huge pages);
/// MemoryError when they cannot be had.
#[pyfunction]
pub fn huge_page_zeros<'py>(py: Python<'py>, len: usize, dtype: &str) -> PyResult<Bound<'py, PyAny>> {
    match dtype {
        "float32" => Ok(zeroed_resident::<f32>(WHAT, len)
            .map_err(py_err)?
            .into_pyarray(py)
            .into_any()),
        "int32" => Ok(zeroed_resident::<i32>(WHAT, len)
            .map_err(py_err)?
            .into_pyarray(py)
            .into_any()),
        "uint16" => Ok(zeroed_resident::<u16>(WHAT, len)
            .map_err(py_err)?
            .into_pyarray(py)
            .into_any()),
        other => Err(InvalidArgumentError::new_err(format!(
            "dtype must be float32, int32 or uint16, got {other}"
        ))),
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(huge_page_zeros, m)?)?;
    Ok(())
}
