//! Camera arguments cross as plain tuples and are validated by the core.

use pyo3::prelude::*;
use urhead_core::Camera;

use crate::errors::py_err;

/// `(K 3×3 row-major, viewmat 4×4 row-major, width, height, near, far)`
pub type CameraArgs = ([[f32; 3]; 3], [[f32; 4]; 4], u32, u32, f32, f32);

pub fn camera(args: CameraArgs) -> PyResult<Camera> {
    let (k, viewmat, width, height, near, far) = args;
    Camera::new(k, viewmat, width, height, near, far).map_err(py_err)
}

/// Validates a camera; raises the error that any kernel would raise for it.
#[pyfunction]
pub fn check_camera(args: CameraArgs) -> PyResult<()> {
    camera(args).map(|_| ())
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(check_camera, m)?)?;
    Ok(())
}
