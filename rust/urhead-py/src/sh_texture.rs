//! Binding of `urhead_core::raster::sh_texture`: a texture lookup shaded with spherical
//! harmonics in one pass (plus a range of channels as they are), forward and adjoint, each
//! entry point serving float32 and float64 (and a float16 texture read in float32).

use half::f16;
use numpy::{Element, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::raster::{self as kernel, ShTextureGradInputs, ShTextureInputs, Texel};
use urhead_core::Real;

use crate::arrays::{array, data, optional, optional_array, optional_shaped_data, shape, with_float_type};
use crate::errors::py_err;
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

fn forward<'py, T: Element + Real, S: Element + Texel<T>>(
    py: Python<'py>,
    tex: Arr<'py, S>,
    uv: Arr<'py, T>,
    dirs: Arr<'py, T>,
    degree: usize,
    extra: (usize, usize),
    wants: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let s = shape(&tex, "tex", 3, "(Ht, Wt, C)")?;
    let n = shape(&uv, "uv", 2, "(N, 2)")?[0];
    shape(&dirs, "dirs", 2, "(N, 3)")?;
    let inputs = ShTextureInputs {
        tex: data(&tex, "tex")?,
        height: s[0],
        width: s[1],
        channels: s[2],
        uv: data(&uv, "uv")?,
        dirs: data(&dirs, "dirs")?,
        degree,
        extra: extra.0..extra.1,
    };
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                kernel::sh_texture_forward(&inputs, wants.0, wants.1)
            })
        })
        .map_err(py_err)?;
    let (e, width) = (inputs.extra.len(), 3 + inputs.extra.len());
    PyTuple::new(
        py,
        [
            array(py, out.rgb, &[n, 3])?.into_any().unbind(),
            array(py, out.extra, &[n, e])?.into_any().unbind(),
            optional(py, out.raw_rgb, &[n, 3])?,
            optional(py, out.slopes, &[n, 2, width])?,
        ],
    )
}

#[allow(clippy::too_many_arguments)]
fn backward<'py, T: Element + Real>(
    py: Python<'py>,
    uv: Arr<'py, T>,
    dirs: Arr<'py, T>,
    degree: usize,
    channels: usize,
    extra: (usize, usize),
    raw_rgb: Arr<'py, T>,
    slopes: Option<Arr<'py, T>>,
    v_rgb: Option<Arr<'py, T>>,
    v_extra: Option<Arr<'py, T>>,
    need_rows: bool,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let n = shape(&uv, "uv", 2, "(N, 2)")?[0];
    shape(&dirs, "dirs", 2, "(N, 3)")?;
    shape(&raw_rgb, "raw_rgb", 2, "(N, 3)")?;
    let v_rgb = optional_shaped_data(&v_rgb, "v_rgb", 2, "(N, 3)")?;
    let v_extra = optional_shaped_data(&v_extra, "v_extra", 2, "(N, E)")?;
    let slopes = optional_shaped_data(&slopes, "slopes", 3, "(N, 2, 3 + E)")?;
    let inputs = ShTextureGradInputs {
        uv: data(&uv, "uv")?,
        dirs: data(&dirs, "dirs")?,
        degree,
        channels,
        extra: extra.0..extra.1,
        raw_rgb: data(&raw_rgb, "raw_rgb")?,
        slopes,
        v_rgb,
        v_extra,
    };
    let g = py
        .allow_threads(|| with_threads(num_threads, || kernel::sh_texture_backward(&inputs, need_rows)))
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            optional(py, g.v_rows, &[n, channels])?,
            optional(py, g.v_uv, &[n, 2])?,
        ],
    )
}

/// `(rgb (N, 3), extra (N, E), raw_rgb (N, 3) or None, slopes (N, 2, 3 + E) or None)`: the
/// SH colour of `tex (Ht, Wt, C)` at `uv (N, 2)` along `dirs (N, 3)`, and the channels
/// `extra = (start, end)`; `wants = (raw_rgb, slopes)`. A float16 `tex` is read in
/// float32 (`uv` and `dirs` float32).
#[pyfunction]
pub fn sh_texture_forward<'py>(
    py: Python<'py>,
    tex: &Bound<'py, PyAny>,
    uv: &Bound<'py, PyAny>,
    dirs: &Bound<'py, PyAny>,
    degree: usize,
    extra: (usize, usize),
    wants: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    if let Ok(half) = tex.downcast::<PyArrayDyn<f16>>() {
        return forward::<f32, f16>(
            py,
            half.readonly(),
            uv.extract()?,
            dirs.extract()?,
            degree,
            extra,
            wants,
            num_threads,
        );
    }
    with_float_type!(tex, T => forward::<T, T>(
        py,
        tex.extract()?,
        uv.extract()?,
        dirs.extract()?,
        degree,
        extra,
        wants,
        num_threads,
    ))
}

/// `(v_rows (N, C) or None, v_uv (N, 2) or None)` from the outputs' gradients `v_rgb (N, 3)`
/// and `v_extra (N, E)` (None for zero) and the forward's saved `raw_rgb` and `slopes` (the
/// UV gradient only with slopes; the rows only with `need_rows`).
#[pyfunction]
#[pyo3(signature = (uv, dirs, degree, channels, extra, raw_rgb, slopes, v_rgb, v_extra, need_rows, num_threads))]
pub fn sh_texture_backward<'py>(
    py: Python<'py>,
    uv: &Bound<'py, PyAny>,
    dirs: &Bound<'py, PyAny>,
    degree: usize,
    channels: usize,
    extra: (usize, usize),
    raw_rgb: &Bound<'py, PyAny>,
    slopes: Option<&Bound<'py, PyAny>>,
    v_rgb: Option<&Bound<'py, PyAny>>,
    v_extra: Option<&Bound<'py, PyAny>>,
    need_rows: bool,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(uv, T => backward::<T>(
        py,
        uv.extract()?,
        dirs.extract()?,
        degree,
        channels,
        extra,
        raw_rgb.extract()?,
        optional_array(slopes)?,
        optional_array(v_rgb)?,
        optional_array(v_extra)?,
        need_rows,
        num_threads,
    ))
}

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(sh_texture_forward, m)?)?;
    m.add_function(wrap_pyfunction!(sh_texture_backward, m)?)?;
    Ok(())
}
