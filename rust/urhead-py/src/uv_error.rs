//! Binding of `urhead_core::uv_error`: one frame's UV error added to the sampling's grids in
//! place (float32 or float64 images), and the nearest covered pixel of every pixel.

use numpy::{Element, PyReadonlyArrayDyn, PyReadwriteArrayDyn};
use pyo3::prelude::*;
use urhead_core::uv_error::{self as kernel, UvErrorInputs};
use urhead_core::Real;

use crate::arrays::{array, data, data_mut, shape, with_float_type};
use crate::errors::py_err;

fn accumulate<T: Element + Real>(
    py: Python<'_>,
    image: PyReadonlyArrayDyn<'_, T>,
    target: PyReadonlyArrayDyn<'_, T>,
    mask: PyReadonlyArrayDyn<'_, T>,
    pixels: PyReadonlyArrayDyn<'_, i64>,
    uv: PyReadonlyArrayDyn<'_, T>,
    mut error: PyReadwriteArrayDyn<'_, f64>,
    mut count: PyReadwriteArrayDyn<'_, f64>,
    side: usize,
) -> PyResult<()> {
    let hw = shape(&image, "image", 3, "(H, W, 3)")?;
    shape(&target, "target", 3, "(H, W, 3)")?;
    shape(&mask, "mask", 2, "(H, W)")?;
    shape(&pixels, "pixels", 1, "(P,)")?;
    shape(&uv, "uv", 2, "(P, 2)")?;
    shape(&error, "error", 1, "(G·G,)")?;
    shape(&count, "count", 1, "(G·G,)")?;
    let inputs = UvErrorInputs {
        image: data(&image, "image")?,
        target: data(&target, "target")?,
        mask: data(&mask, "mask")?,
        pixels: data(&pixels, "pixels")?,
        uv: data(&uv, "uv")?,
        height: hw[0],
        width: hw[1],
    };
    let (error, count) = (data_mut(&mut error, "error")?, data_mut(&mut count, "count")?);
    py.allow_threads(|| kernel::accumulate_uv_error(&inputs, side, error, count))
        .map_err(py_err)
}

/// Adds the frame's error ‖image − target‖₁·mask of the (H, W, 3) images and (H, W) mask
/// to the (G·G,) float64 `error` and `count` grids (G = `side`) at the UVs (P, 2) of the
/// covered pixels (P,) int64, and at the nearest covered pixel's UV for pixels inside the
/// mask the mesh misses.
#[pyfunction]
pub fn accumulate_uv_error<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    target: &Bound<'py, PyAny>,
    mask: &Bound<'py, PyAny>,
    pixels: &Bound<'py, PyAny>,
    uv: &Bound<'py, PyAny>,
    error: &Bound<'py, PyAny>,
    count: &Bound<'py, PyAny>,
    side: usize,
) -> PyResult<()> {
    with_float_type!(image, T => accumulate::<T>(
        py,
        image.extract()?,
        target.extract()?,
        mask.extract()?,
        pixels.extract()?,
        uv.extract()?,
        error.extract()?,
        count.extract()?,
        side,
    ))
}

/// (H·W,) int64 flat index of the nearest pixel where the (H, W) bool `covered` is true,
/// −1 everywhere when none is.
#[pyfunction]
pub fn nearest_covered<'py>(
    py: Python<'py>,
    covered: PyReadonlyArrayDyn<'py, bool>,
) -> PyResult<Bound<'py, PyAny>> {
    let hw = shape(&covered, "covered", 2, "(H, W)")?;
    let flags = data(&covered, "covered")?;
    let nearest = py
        .allow_threads(|| kernel::nearest_covered(flags, hw[0], hw[1]))
        .map_err(py_err)?;
    Ok(array(py, nearest, &[hw[0] * hw[1]])?.into_any())
}

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(accumulate_uv_error, m)?)?;
    m.add_function(wrap_pyfunction!(nearest_covered, m)?)?;
    Ok(())
}
