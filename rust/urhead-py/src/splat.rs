//! Binding of `urhead_core::splat`: projection and rasterization, each entry point serving
//! float32 and float64 through one generic body. What the rasterizer's backward needs from its
//! forward crosses back to Python as an opaque `SplatState` object.

use numpy::{Element, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::splat::{
    project_backward, project_forward, rasterize_backward, rasterize_forward, Background, Binning,
    ProjectGradOutputs, ProjectInputs, ProjectNeeds, RasterInputs, ShCoeffs, SplatReal,
};

use crate::arrays::{array, data, optional, optional_array, shape, with_float_type};
use crate::camera::{camera, CameraArgs};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// What one forward rasterization keeps for its backward: the tile lists.
#[pyclass(frozen, module = "urhead._core")]
pub struct SplatState {
    binning: Binning,
}

#[pymethods]
impl SplatState {
    /// Number of (tile, Gaussian) intersections.
    #[getter]
    fn num_intersections(&self) -> usize {
        self.binning.num_intersections()
    }
}

fn none_or<'py>(py: Python<'py>, x: Option<Bound<'py, PyAny>>) -> PyObject {
    x.map_or_else(|| py.None(), |a| a.unbind())
}

fn project_inputs<'a, T: Element + SplatReal>(
    means: &'a Arr<'_, T>,
    quats: &'a Arr<'_, T>,
    scales: &'a Arr<'_, T>,
    opacities: &'a Arr<'_, T>,
    sh: Option<&'a Arr<'_, T>>,
    sh_degree: usize,
) -> PyResult<ProjectInputs<'a, T>> {
    let n = shape(means, "means", 2, "(N, 3)")?[0];
    shape(quats, "quats", 2, "(N, 4)")?;
    shape(scales, "scales", 2, "(N, 3)")?;
    shape(opacities, "opacities", 1, "(N,)")?;
    let sh = match sh {
        Some(a) => {
            let s = shape(a, "sh", 3, "(N, K, 3)")?;
            if s[2] != 3 || s[0] != n {
                return Err(ShapeError::new_err(format!(
                    "sh must be (N, K, 3) with N = {n}, got {s:?}"
                )));
            }
            Some(ShCoeffs {
                coeffs: data(a, "sh")?,
                num_coeffs: s[1],
                degree: sh_degree,
            })
        }
        None => None,
    };
    Ok(ProjectInputs {
        means: data(means, "means")?,
        quats: data(quats, "quats")?,
        scales: data(scales, "scales")?,
        opacities: data(opacities, "opacities")?,
        sh,
        num_gaussians: n,
    })
}

#[allow(clippy::type_complexity)]
fn raster_inputs<'a, T: Element + SplatReal>(
    arrays: &'a (
        Arr<'_, T>,
        Arr<'_, T>,
        Arr<'_, T>,
        Arr<'_, T>,
        Arr<'_, T>,
        Arr<'_, i32>,
    ),
    background: Option<&'a Arr<'_, T>>,
    depth_map: Option<&'a Arr<'_, T>>,
    depth_eps: T,
    width: usize,
    height: usize,
) -> PyResult<RasterInputs<'a, T>> {
    let (means2d, conics, colors, opacities, depths, radii) = arrays;
    let n = shape(means2d, "means2d", 2, "(N, 2)")?[0];
    shape(conics, "conics", 2, "(N, 3)")?;
    let c = shape(colors, "colors", 2, "(N, C)")?[1];
    shape(opacities, "opacities", 1, "(N,)")?;
    shape(depths, "depths", 1, "(N,)")?;
    shape(radii, "radii", 2, "(N, 2)")?;
    if let Some(d) = depth_map {
        let s = shape(d, "depth_map", 2, "(H, W)")?;
        if s != [height, width] {
            return Err(ShapeError::new_err(format!(
                "depth_map must be (H, W) = ({height}, {width}), got {s:?}"
            )));
        }
    }
    let background = background.map(|b| background_of(b, height, width)).transpose()?;
    Ok(RasterInputs {
        means2d: data(means2d, "means2d")?,
        conics: data(conics, "conics")?,
        colors: data(colors, "colors")?,
        opacities: data(opacities, "opacities")?,
        depths: data(depths, "depths")?,
        radii: data(radii, "radii")?,
        num_gaussians: n,
        channels: c,
        width,
        height,
        background,
        depth_map: depth_map.map(|d| data(d, "depth_map")).transpose()?,
        depth_eps,
    })
}

/// A uniform `(C,)` background, or an image `(H, W, S)` behind the Gaussians.
fn background_of<'a, T: Element + SplatReal>(
    b: &'a Arr<'_, T>,
    height: usize,
    width: usize,
) -> PyResult<Background<'a, T>> {
    let s = b.shape().to_vec();
    match s[..] {
        [_] => Ok(Background::Uniform(data(b, "background")?)),
        [bh, bw, channels] if (bh, bw) == (height, width) => Ok(Background::Image {
            values: data(b, "background")?,
            channels,
        }),
        _ => Err(ShapeError::new_err(format!(
            "background must be (C,) or (H, W, S) = ({height}, {width}, S), got shape {s:?}"
        ))),
    }
}

#[allow(clippy::too_many_arguments)]
fn project_forward_typed<'py, T: Element + SplatReal>(
    py: Python<'py>,
    means: Arr<'py, T>,
    quats: Arr<'py, T>,
    scales: Arr<'py, T>,
    opacities: Arr<'py, T>,
    sh: Option<Arr<'py, T>>,
    sh_degree: usize,
    camera_args: CameraArgs,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let cam = camera(camera_args)?;
    let inputs = project_inputs(&means, &quats, &scales, &opacities, sh.as_ref(), sh_degree)?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || project_forward(&cam, &inputs)))
        .map_err(py_err)?;
    let n = inputs.num_gaussians;
    let colors = out.colors.map(|c| array(py, c, &[n, 3])).transpose()?;
    PyTuple::new(
        py,
        [
            array(py, out.means2d, &[n, 2])?.into_any().unbind(),
            array(py, out.conics, &[n, 3])?.into_any().unbind(),
            array(py, out.depths, &[n])?.into_any().unbind(),
            array(py, out.radii, &[n, 2])?.into_any().unbind(),
            none_or(py, colors.map(|c| c.into_any())),
        ],
    )
}

#[allow(clippy::too_many_arguments)]
fn project_backward_typed<'py, T: Element + SplatReal>(
    py: Python<'py>,
    means: Arr<'py, T>,
    quats: Arr<'py, T>,
    scales: Arr<'py, T>,
    opacities: Arr<'py, T>,
    sh: Option<Arr<'py, T>>,
    sh_degree: usize,
    camera_args: CameraArgs,
    v_means2d: Option<Arr<'py, T>>,
    v_conics: Option<Arr<'py, T>>,
    v_colors: Option<Arr<'py, T>>,
    needs: (bool, bool, bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let cam = camera(camera_args)?;
    let inputs = project_inputs(&means, &quats, &scales, &opacities, sh.as_ref(), sh_degree)?;
    let grads = ProjectGradOutputs {
        v_means2d: v_means2d.as_ref().map(|a| data(a, "v_means2d")).transpose()?,
        v_conics: v_conics.as_ref().map(|a| data(a, "v_conics")).transpose()?,
        v_colors: v_colors.as_ref().map(|a| data(a, "v_colors")).transpose()?,
    };
    let needs = ProjectNeeds {
        means: needs.0,
        quats: needs.1,
        scales: needs.2,
        sh: needs.3,
    };
    let g = py
        .allow_threads(|| with_threads(num_threads, || project_backward(&cam, &inputs, &grads, &needs)))
        .map_err(py_err)?;
    let n = inputs.num_gaussians;
    let k = inputs.sh.map_or(0, |s| s.num_coeffs);
    PyTuple::new(
        py,
        [
            optional(py, g.v_means, &[n, 3])?,
            optional(py, g.v_quats, &[n, 4])?,
            optional(py, g.v_scales, &[n, 3])?,
            optional(py, g.v_sh, &[n, k, 3])?,
        ],
    )
}

#[allow(clippy::too_many_arguments)]
fn rasterize_forward_typed<'py, T: Element + SplatReal>(
    py: Python<'py>,
    means2d: Arr<'py, T>,
    conics: Arr<'py, T>,
    colors: Arr<'py, T>,
    opacities: Arr<'py, T>,
    depths: Arr<'py, T>,
    radii: Arr<'py, i32>,
    background: Option<Arr<'py, T>>,
    depth_map: Option<Arr<'py, T>>,
    depth_eps: T,
    width: usize,
    height: usize,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let arrays = (means2d, conics, colors, opacities, depths, radii);
    let inputs = raster_inputs(
        &arrays,
        background.as_ref(),
        depth_map.as_ref(),
        depth_eps,
        width,
        height,
    )?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || rasterize_forward(&inputs)))
        .map_err(py_err)?;
    let state = SplatState { binning: out.binning };
    let c = inputs.channels;
    PyTuple::new(
        py,
        [
            array(py, out.image, &[height, width, c])?.into_any().unbind(),
            array(py, out.transmittance, &[height, width])?
                .into_any()
                .unbind(),
            Py::new(py, state)?.into_any(),
            out.evaluated_pairs.into_pyobject(py)?.into_any().unbind(),
        ],
    )
}

#[allow(clippy::too_many_arguments)]
fn rasterize_backward_typed<'py, T: Element + SplatReal>(
    py: Python<'py>,
    state: PyRef<'py, SplatState>,
    means2d: Arr<'py, T>,
    conics: Arr<'py, T>,
    colors: Arr<'py, T>,
    opacities: Arr<'py, T>,
    depths: Arr<'py, T>,
    radii: Arr<'py, i32>,
    background: Option<Arr<'py, T>>,
    depth_map: Option<Arr<'py, T>>,
    depth_eps: T,
    width: usize,
    height: usize,
    v_image: Option<Arr<'py, T>>,
    v_transmittance: Option<Arr<'py, T>>,
    transmittance: Option<Arr<'py, T>>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let arrays = (means2d, conics, colors, opacities, depths, radii);
    let inputs = raster_inputs(
        &arrays,
        background.as_ref(),
        depth_map.as_ref(),
        depth_eps,
        width,
        height,
    )?;
    let v_image = v_image.as_ref().map(|a| data(a, "v_image")).transpose()?;
    let v_t = v_transmittance
        .as_ref()
        .map(|a| data(a, "v_transmittance"))
        .transpose()?;
    let bins = &state.binning;
    let (n, c) = (inputs.num_gaussians, inputs.channels);
    let behind = match inputs.background {
        Some(Background::Image { channels, .. }) => Some(channels),
        _ => None,
    };
    let t = transmittance
        .as_ref()
        .map(|a| data(a, "transmittance"))
        .transpose()?;
    let g = py
        .allow_threads(|| with_threads(num_threads, || rasterize_backward(&inputs, bins, v_image, v_t, t)))
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            array(py, g.v_means2d, &[n, 2])?.into_any().unbind(),
            array(py, g.v_conics, &[n, 3])?.into_any().unbind(),
            array(py, g.v_colors, &[n, c])?.into_any().unbind(),
            array(py, g.v_opacities, &[n])?.into_any().unbind(),
            optional(py, g.v_background, &[height, width, behind.unwrap_or(0)])?,
        ],
    )
}

/// Projection → (means2d, conics, depths, radii, colors or None).
#[pyfunction]
#[pyo3(signature = (means, quats, scales, opacities, sh, sh_degree, camera_args, num_threads))]
pub fn splat_project_forward<'py>(
    py: Python<'py>,
    means: &Bound<'py, PyAny>,
    quats: &Bound<'py, PyAny>,
    scales: &Bound<'py, PyAny>,
    opacities: &Bound<'py, PyAny>,
    sh: Option<&Bound<'py, PyAny>>,
    sh_degree: usize,
    camera_args: CameraArgs,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(means, T => project_forward_typed::<T>(
        py,
        means.extract()?,
        quats.extract()?,
        scales.extract()?,
        opacities.extract()?,
        optional_array(sh)?,
        sh_degree,
        camera_args,
        num_threads,
    ))
}

/// Projection backward → (v_means, v_quats, v_scales, v_sh), None where not needed.
#[pyfunction]
#[pyo3(signature = (means, quats, scales, opacities, sh, sh_degree, camera_args, v_means2d, v_conics, v_colors, needs, num_threads))]
pub fn splat_project_backward<'py>(
    py: Python<'py>,
    means: &Bound<'py, PyAny>,
    quats: &Bound<'py, PyAny>,
    scales: &Bound<'py, PyAny>,
    opacities: &Bound<'py, PyAny>,
    sh: Option<&Bound<'py, PyAny>>,
    sh_degree: usize,
    camera_args: CameraArgs,
    v_means2d: Option<&Bound<'py, PyAny>>,
    v_conics: Option<&Bound<'py, PyAny>>,
    v_colors: Option<&Bound<'py, PyAny>>,
    needs: (bool, bool, bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(means, T => project_backward_typed::<T>(
        py,
        means.extract()?,
        quats.extract()?,
        scales.extract()?,
        opacities.extract()?,
        optional_array(sh)?,
        sh_degree,
        camera_args,
        optional_array(v_means2d)?,
        optional_array(v_conics)?,
        optional_array(v_colors)?,
        needs,
        num_threads,
    ))
}

/// Rasterization → (image, transmittance, state for the backward, evaluated pairs).
#[pyfunction]
#[pyo3(signature = (means2d, conics, colors, opacities, depths, radii, background, depth_map, depth_eps, width, height, num_threads))]
pub fn splat_rasterize_forward<'py>(
    py: Python<'py>,
    means2d: &Bound<'py, PyAny>,
    conics: &Bound<'py, PyAny>,
    colors: &Bound<'py, PyAny>,
    opacities: &Bound<'py, PyAny>,
    depths: &Bound<'py, PyAny>,
    radii: Arr<'py, i32>,
    background: Option<&Bound<'py, PyAny>>,
    depth_map: Option<&Bound<'py, PyAny>>,
    depth_eps: &Bound<'py, PyAny>,
    width: usize,
    height: usize,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(means2d, T => rasterize_forward_typed::<T>(
        py,
        means2d.extract()?,
        conics.extract()?,
        colors.extract()?,
        opacities.extract()?,
        depths.extract()?,
        radii,
        optional_array(background)?,
        optional_array(depth_map)?,
        depth_eps.extract()?,
        width,
        height,
        num_threads,
    ))
}

/// Rasterization backward → (v_means2d, v_conics, v_colors, v_opacities, v_background:
/// (H, W, S) for an image background, which needs the forward's `transmittance`, else
/// None).
#[pyfunction]
#[pyo3(signature = (state, means2d, conics, colors, opacities, depths, radii, background, depth_map, depth_eps, width, height, v_image, v_transmittance, transmittance, num_threads))]
pub fn splat_rasterize_backward<'py>(
    py: Python<'py>,
    state: PyRef<'py, SplatState>,
    means2d: &Bound<'py, PyAny>,
    conics: &Bound<'py, PyAny>,
    colors: &Bound<'py, PyAny>,
    opacities: &Bound<'py, PyAny>,
    depths: &Bound<'py, PyAny>,
    radii: Arr<'py, i32>,
    background: Option<&Bound<'py, PyAny>>,
    depth_map: Option<&Bound<'py, PyAny>>,
    depth_eps: &Bound<'py, PyAny>,
    width: usize,
    height: usize,
    v_image: Option<&Bound<'py, PyAny>>,
    v_transmittance: Option<&Bound<'py, PyAny>>,
    transmittance: Option<&Bound<'py, PyAny>>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(means2d, T => rasterize_backward_typed::<T>(
        py,
        state,
        means2d.extract()?,
        conics.extract()?,
        colors.extract()?,
        opacities.extract()?,
        depths.extract()?,
        radii,
        optional_array(background)?,
        optional_array(depth_map)?,
        depth_eps.extract()?,
        width,
        height,
        optional_array(v_image)?,
        optional_array(v_transmittance)?,
        optional_array(transmittance)?,
        num_threads,
    ))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<SplatState>()?;
    m.add_function(wrap_pyfunction!(splat_project_forward, m)?)?;
    m.add_function(wrap_pyfunction!(splat_project_backward, m)?)?;
    m.add_function(wrap_pyfunction!(splat_rasterize_forward, m)?)?;
    m.add_function(wrap_pyfunction!(splat_rasterize_backward, m)?)?;
    Ok(())
}
