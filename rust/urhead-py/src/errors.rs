//! Core errors → specific Python exceptions (all subclasses of the builtin a user would
//! catch: ValueError for bad arguments, MemoryError for size limits).

use pyo3::create_exception;
use pyo3::exceptions::{PyMemoryError, PyValueError};
use pyo3::prelude::*;
use urhead_core::Error;

create_exception!(_core, ShapeError, PyValueError, "A tensor has the wrong shape.");
create_exception!(
    _core,
    NonFiniteError,
    PyValueError,
    "A tensor holds NaN or infinity."
);
create_exception!(
    _core,
    IndexRangeError,
    PyValueError,
    "An index tensor points out of range."
);
create_exception!(
    _core,
    InvalidArgumentError,
    PyValueError,
    "An argument is invalid."
);
create_exception!(_core, SizeLimitError, PyMemoryError, "A size exceeds a limit.");

/// Maps a core error to its Python exception, keeping the message that names the argument.
pub fn py_err(e: Error) -> PyErr {
    let msg = e.to_string();
    match e {
        Error::Shape { .. } => ShapeError::new_err(msg),
        Error::NonFinite { .. } => NonFiniteError::new_err(msg),
        Error::IndexOutOfRange { .. } => IndexRangeError::new_err(msg),
        Error::Invalid { .. } => InvalidArgumentError::new_err(msg),
        Error::TooLarge { .. } => SizeLimitError::new_err(msg),
        Error::OutOfMemory { .. } => PyMemoryError::new_err(msg),
    }
}

/// The exception types, as `urhead._core.<Name>` (urhead.errors re-exports them).
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("ShapeError", py.get_type::<ShapeError>())?;
    m.add("NonFiniteError", py.get_type::<NonFiniteError>())?;
    m.add("IndexRangeError", py.get_type::<IndexRangeError>())?;
    m.add("InvalidArgumentError", py.get_type::<InvalidArgumentError>())?;
    m.add("SizeLimitError", py.get_type::<SizeLimitError>())?;
    Ok(())
}
