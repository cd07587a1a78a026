//! Binding of `urhead_core::ssim`: masked SSIM and L1 of `(H, W, C)` images, chosen by
//! name, as a value-only entry point and a value-with-gradient one, and the two together
//! with one gradient; and the L1 of values at listed pixels against an image (the normal
//! loss); each serving float32 and float64.

use numpy::{Element, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use urhead_core::ssim::{self, SsimInputs};
use urhead_core::{Real, Result};

use crate::arrays::{array, data, optional_array, shape, with_float_type};
use crate::errors::{py_err, InvalidArgumentError, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// The core's inputs; the image may hold more channels than the target (S ≥ C, its first
/// C compared) for L1 only.
fn inputs<'a, T: Element + Real>(
    metric: &str,
    image: &'a Arr<'_, T>,
    target: &'a Arr<'_, T>,
    mask: Option<&'a Arr<'_, T>>,
) -> PyResult<SsimInputs<'a, T>> {
    let image_dims = shape(image, "image", 3, "(H, W, C)")?;
    let dims = shape(target, "target", 3, "(H, W, C)")?;
    let wider = metric == "l1" && image_dims[2] > dims[2];
    if image_dims[..2] != dims[..2] || (image_dims[2] != dims[2] && !wider) {
        return Err(ShapeError::new_err(format!(
            "target must have the image's shape {image_dims:?} (for l1, the image may hold \
             more channels, its first C compared), got {dims:?}"
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
        image_channels: image_dims[2],
    })
}

fn value<T: Element + Real>(
    py: Python<'_>,
    metric: &str,
    kernel: fn(&SsimInputs<'_, T>) -> Result<T>,
    image: Arr<'_, T>,
    target: Arr<'_, T>,
    mask: Option<Arr<'_, T>>,
    num_threads: usize,
) -> PyResult<f64> {
    let inputs = inputs(metric, &image, &target, mask.as_ref())?;
    let v = py
        .allow_threads(|| with_threads(num_threads, || kernel(&inputs)))
        .map_err(py_err)?;
    Ok(v.to_f64().unwrap_or(f64::NAN))
}

#[allow(clippy::type_complexity)]
fn value_and_grad<'py, T: Element + Real>(
    py: Python<'py>,
    metric: &str,
    kernel: fn(&SsimInputs<'_, T>, f64) -> Result<(T, Vec<T>)>,
    image: Arr<'py, T>,
    target: Arr<'py, T>,
    mask: Option<Arr<'py, T>>,
    weight: f64,
    num_threads: usize,
) -> PyResult<(f64, Bound<'py, PyAny>)> {
    let inputs = inputs(metric, &image, &target, mask.as_ref())?;
    let (v, grad) = py
        .allow_threads(|| with_threads(num_threads, || kernel(&inputs, weight)))
        .map_err(py_err)?;
    let dims = [inputs.height, inputs.width, inputs.image_channels];
    Ok((v.to_f64().unwrap_or(f64::NAN), array(py, grad, &dims)?.into_any()))
}

/// The core kernels of `metric` ("ssim" or "l1"): value, and value with gradient.
#[allow(clippy::type_complexity)]
fn kernels<T: Real>(
    metric: &str,
) -> PyResult<(
    fn(&SsimInputs<'_, T>) -> Result<T>,
    fn(&SsimInputs<'_, T>, f64) -> Result<(T, Vec<T>)>,
)> {
    match metric {
        "ssim" => Ok((ssim::masked_ssim::<T>, ssim::masked_ssim_with_grad::<T>)),
        "l1" => Ok((ssim::masked_l1::<T>, ssim::masked_l1_with_grad::<T>)),
        _ => Err(InvalidArgumentError::new_err(format!(
            "metric must be \"ssim\" or \"l1\", got {metric:?}"
        ))),
    }
}

/// Masked mean `metric` ("ssim" or "l1": mean absolute difference) of (H, W, C) images;
/// mask (H, W) or None.
#[pyfunction]
pub fn masked_mean<'py>(
    py: Python<'py>,
    metric: &str,
    image: &Bound<'py, PyAny>,
    target: &Bound<'py, PyAny>,
    mask: Option<&Bound<'py, PyAny>>,
    num_threads: usize,
) -> PyResult<f64> {
    with_float_type!(image, T => value(
        py,
        metric,
        kernels::<T>(metric)?.0,
        image.extract()?,
        target.extract()?,
        optional_array(mask)?,
        num_threads,
    ))
}

/// Masked mean `metric` and the (H, W, C) gradient of `weight ·` it in `image`.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub fn masked_mean_grad<'py>(
    py: Python<'py>,
    metric: &str,
    image: &Bound<'py, PyAny>,
    target: &Bound<'py, PyAny>,
    mask: Option<&Bound<'py, PyAny>>,
    weight: f64,
    num_threads: usize,
) -> PyResult<(f64, Bound<'py, PyAny>)> {
    with_float_type!(image, T => value_and_grad(
        py,
        metric,
        kernels::<T>(metric)?.1,
        image.extract()?,
        target.extract()?,
        optional_array(mask)?,
        weight,
        num_threads,
    ))
}

/// Masked mean SSIM and L1 of (H, W, C) images, and the (H, W, C) gradient of
/// `ssim_weight · SSIM + l1_weight · L1` in `image`, in one pass: `(ssim, l1, grad)`.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub fn masked_ssim_l1_grad<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    target: &Bound<'py, PyAny>,
    mask: Option<&Bound<'py, PyAny>>,
    ssim_weight: f64,
    l1_weight: f64,
    num_threads: usize,
) -> PyResult<(f64, f64, Bound<'py, PyAny>)> {
    with_float_type!(image, T => ssim_l1_and_grad::<T>(
        py,
        image.extract()?,
        target.extract()?,
        optional_array(mask)?,
        (ssim_weight, l1_weight),
        num_threads,
    ))
}

#[allow(clippy::type_complexity)]
fn ssim_l1_and_grad<'py, T: Element + Real>(
    py: Python<'py>,
    image: Arr<'py, T>,
    target: Arr<'py, T>,
    mask: Option<Arr<'py, T>>,
    (ssim_weight, l1_weight): (f64, f64),
    num_threads: usize,
) -> PyResult<(f64, f64, Bound<'py, PyAny>)> {
    let inputs = inputs("ssim", &image, &target, mask.as_ref())?;
    let (ssim, l1, grad) = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                ssim::masked_ssim_l1_with_grad(&inputs, ssim_weight, l1_weight)
            })
        })
        .map_err(py_err)?;
    let dims = [inputs.height, inputs.width, inputs.channels];
    Ok((
        ssim.to_f64().unwrap_or(f64::NAN),
        l1.to_f64().unwrap_or(f64::NAN),
        array(py, grad, &dims)?.into_any(),
    ))
}

/// Mean L1 of `values (P, C)` against `target (H, W, C)` at their `pixels (P,)`, weighted by
/// `mask (H, W)` where the target holds data, and the (P, C) gradient of `weight ·` it.
#[pyfunction]
pub fn pixel_l1_grad<'py>(
    py: Python<'py>,
    values: &Bound<'py, PyAny>,
    pixels: Arr<'py, i64>,
    target: &Bound<'py, PyAny>,
    mask: &Bound<'py, PyAny>,
    weight: f64,
    num_threads: usize,
) -> PyResult<(f64, Bound<'py, PyAny>)> {
    with_float_type!(values, T => pixel_l1_and_grad::<T>(
        py,
        values.extract()?,
        pixels,
        target.extract()?,
        mask.extract()?,
        weight,
        num_threads,
    ))
}

fn pixel_l1_and_grad<'py, T: Element + Real>(
    py: Python<'py>,
    values: Arr<'py, T>,
    pixels: Arr<'py, i64>,
    target: Arr<'py, T>,
    mask: Arr<'py, T>,
    weight: f64,
    num_threads: usize,
) -> PyResult<(f64, Bound<'py, PyAny>)> {
    let dims = shape(&values, "values", 2, "(P, C)")?;
    shape(&pixels, "pixels", 1, "(P,)")?;
    let image = shape(&target, "target", 3, "(H, W, C)")?;
    let mask_dims = shape(&mask, "mask", 2, "(H, W)")?;
    if image[2] != dims[1] || mask_dims[..] != image[..2] {
        return Err(ShapeError::new_err(format!(
            "target must be (H, W, C) with the values' C = {} and mask (H, W), got {image:?} and {mask_dims:?}",
            dims[1]
        )));
    }
    let inputs = ssim::PixelL1Inputs {
        values: data(&values, "values")?,
        pixels: data(&pixels, "pixels")?,
        target: data(&target, "target")?,
        mask: data(&mask, "mask")?,
        channels: dims[1],
    };
    let (v, grad) = py
        .allow_threads(|| with_threads(num_threads, || ssim::pixel_l1_with_grad(&inputs, weight)))
        .map_err(py_err)?;
    Ok((v.to_f64().unwrap_or(f64::NAN), array(py, grad, &dims)?.into_any()))
}

/// Adds the entry points to `_core`.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(masked_mean, m)?)?;
    m.add_function(wrap_pyfunction!(masked_mean_grad, m)?)?;
    m.add_function(wrap_pyfunction!(masked_ssim_l1_grad, m)?)?;
    m.add_function(wrap_pyfunction!(pixel_l1_grad, m)?)?;
    Ok(())
}
