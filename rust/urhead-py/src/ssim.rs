//! Binding of `urhead_core::ssim`: masked SSIM and L1 of `(H, W, C)` images, each as a
//! value-only entry point and a value-with-gradient one, in float32 and float64.

use numpy::{Element, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use urhead_core::ssim::{masked_l1, masked_l1_with_grad, masked_ssim, masked_ssim_with_grad, SsimInputs};
use urhead_core::{Real, Result};

use crate::arrays::{array, data, shape};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

fn inputs<'a, T: Element + Real>(
    image: &'a Arr<'_, T>,
    target: &'a Arr<'_, T>,
    mask: Option<&'a Arr<'_, T>>,
) -> PyResult<SsimInputs<'a, T>> {
    let dims = shape(image, "image", 3, "(H, W, C)")?;
    let target_dims = shape(target, "target", 3, "(H, W, C)")?;
    if target_dims != dims {
        return Err(ShapeError::new_err(format!(
            "target must have the image's shape {dims:?}, got {target_dims:?}"
        )));
    }
    let mask = match mask {
        Some(m) => {
            let mask_dims = shape(m, "mask", 2, "(H, W)")?;
            if mask_dims[..] != dims[..2] {
                return Err(ShapeError::new_err(format!(
                    "mask must be (H, W) = ({}, {}), got {mask_dims:?}",
                    dims[0], dims[1]
                )));
            }
            Some(data(m, "mask")?)
        }
        None => None,
    };
    Ok(SsimInputs {
        image: data(image, "image")?,
        target: data(target, "target")?,
        mask,
        height: dims[0],
        width: dims[1],
        channels: dims[2],
    })
}

fn value<T: Element + Real>(
    py: Python<'_>,
    kernel: fn(&SsimInputs<'_, T>) -> Result<T>,
    image: Arr<'_, T>,
    target: Arr<'_, T>,
    mask: Option<Arr<'_, T>>,
    num_threads: usize,
) -> PyResult<f64> {
    let inputs = inputs(&image, &target, mask.as_ref())?;
    let v = py
        .allow_threads(|| with_threads(num_threads, || kernel(&inputs)))
        .map_err(py_err)?;
    Ok(v.to_f64().unwrap_or(f64::NAN))
}

#[allow(clippy::type_complexity)]
fn value_and_grad<'py, T: Element + Real>(
    py: Python<'py>,
    kernel: fn(&SsimInputs<'_, T>) -> Result<(T, Vec<T>)>,
    image: Arr<'py, T>,
    target: Arr<'py, T>,
    mask: Option<Arr<'py, T>>,
    num_threads: usize,
) -> PyResult<(f64, Bound<'py, numpy::PyArrayDyn<T>>)> {
    let inputs = inputs(&image, &target, mask.as_ref())?;
    let (v, grad) = py
        .allow_threads(|| with_threads(num_threads, || kernel(&inputs)))
        .map_err(py_err)?;
    let dims = [inputs.height, inputs.width, inputs.channels];
    Ok((v.to_f64().unwrap_or(f64::NAN), array(py, grad, &dims)?))
}

macro_rules! entry_points {
    ($value:ident, $grad:ident, $kernel:ident, $kernel_grad:ident, $what:literal, $t:ty) => {
        #[doc = concat!("Masked mean ", $what, " of (H, W, C) images; mask (H, W) or None.")]
        #[pyfunction]
        pub fn $value(
            py: Python<'_>,
            image: Arr<'_, $t>,
            target: Arr<'_, $t>,
            mask: Option<Arr<'_, $t>>,
            num_threads: usize,
        ) -> PyResult<f64> {
            value(py, $kernel::<$t>, image, target, mask, num_threads)
        }

        #[doc = concat!("Masked mean ", $what, " and its (H, W, C) gradient in `image`.")]
        #[pyfunction]
        pub fn $grad<'py>(
            py: Python<'py>,
            image: Arr<'py, $t>,
            target: Arr<'py, $t>,
            mask: Option<Arr<'py, $t>>,
            num_threads: usize,
        ) -> PyResult<(f64, Bound<'py, numpy::PyArrayDyn<$t>>)> {
            value_and_grad(py, $kernel_grad::<$t>, image, target, mask, num_threads)
        }
    };
}

entry_points!(
    masked_ssim_f32,
    masked_ssim_grad_f32,
    masked_ssim,
    masked_ssim_with_grad,
    "SSIM",
    f32
);
entry_points!(
    masked_ssim_f64,
    masked_ssim_grad_f64,
    masked_ssim,
    masked_ssim_with_grad,
    "SSIM",
    f64
);
entry_points!(
    masked_l1_f32,
    masked_l1_grad_f32,
    masked_l1,
    masked_l1_with_grad,
    "absolute difference",
    f32
);
entry_points!(
    masked_l1_f64,
    masked_l1_grad_f64,
    masked_l1,
    masked_l1_with_grad,
    "absolute difference",
    f64
);

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(masked_ssim_f32, m)?)?;
    m.add_function(wrap_pyfunction!(masked_ssim_grad_f32, m)?)?;
    m.add_function(wrap_pyfunction!(masked_l1_f32, m)?)?;
    m.add_function(wrap_pyfunction!(masked_l1_grad_f32, m)?)?;
    m.add_function(wrap_pyfunction!(masked_ssim_f64, m)?)?;
    m.add_function(wrap_pyfunction!(masked_ssim_grad_f64, m)?)?;
    m.add_function(wrap_pyfunction!(masked_l1_f64, m)?)?;
    m.add_function(wrap_pyfunction!(masked_l1_grad_f64, m)?)?;
    Ok(())
}
