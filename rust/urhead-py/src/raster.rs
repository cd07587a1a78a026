//! Binding of `urhead_core::raster`: each entry point serves float32 and float64 through a
//! generic body, which validates shapes, releases the GIL and runs the core on the pool.

use numpy::{Element, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::raster::{
    self, AntialiasInputs, RasterSetup, ScatterInputs, SilhouetteBlends, PACKED_BLEND,
};
use urhead_core::Real;

use crate::arrays::{array, data, optional, optional_data, shape, with_float_type};
use crate::camera::{camera, CameraArgs};
use crate::errors::{py_err, InvalidArgumentError, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// Checks `ndim` and the size of the last axis; returns the shape.
fn shape_last<T: Element>(
    arr: &Arr<'_, T>,
    arg: &str,
    ndim: usize,
    last: usize,
    layout: &str,
) -> PyResult<Vec<usize>> {
    let s = shape(arr, arg, ndim, layout)?;
    if s[ndim - 1] != last {
        return Err(ShapeError::new_err(format!(
            "{arg} must be {layout}, got shape {:?}",
            arr.shape()
        )));
    }
    Ok(s)
}

fn image_dims<T: Element>(
    arr: &Arr<'_, T>,
    arg: &str,
    ndim: usize,
    layout: &str,
) -> PyResult<(usize, usize)> {
    let s = shape(arr, arg, ndim, layout)?;
    Ok((s[0], s[1]))
}

/// What one forward rasterization keeps for its backward: the triangles' setup.
#[pyclass(frozen, module = "urhead._core")]
pub struct RasterState {
    setup: KeptSetup,
}

enum KeptSetup {
    F32(RasterSetup<f32>),
    F64(RasterSetup<f64>),
}

/// The float types a [`RasterState`] holds a setup of.
trait KeptReal: Real + Element {
    fn keep(setup: RasterSetup<Self>) -> KeptSetup;
    fn kept(state: &KeptSetup) -> Option<&RasterSetup<Self>>;
}

impl KeptReal for f32 {
    fn keep(setup: RasterSetup<f32>) -> KeptSetup {
        KeptSetup::F32(setup)
    }
    fn kept(state: &KeptSetup) -> Option<&RasterSetup<f32>> {
        match state {
            KeptSetup::F32(s) => Some(s),
            KeptSetup::F64(_) => None,
        }
    }
}

impl KeptReal for f64 {
    fn keep(setup: RasterSetup<f64>) -> KeptSetup {
        KeptSetup::F64(setup)
    }
    fn kept(state: &KeptSetup) -> Option<&RasterSetup<f64>> {
        match state {
            KeptSetup::F64(s) => Some(s),
            KeptSetup::F32(_) => None,
        }
    }
}

fn rasterize_forward_typed<'py, T: KeptReal>(
    py: Python<'py>,
    verts: Arr<'py, T>,
    faces: Arr<'py, i32>,
    camera_args: CameraArgs,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    shape_last(&verts, "verts", 2, 3, "(V, 3)")?;
    shape_last(&faces, "faces", 2, 3, "(F, 3) int32")?;
    let cam = camera(camera_args)?;
    let (v, f) = (data(&verts, "verts")?, data(&faces, "faces")?);
    let (out, setup) = py
        .allow_threads(|| with_threads(num_threads, || raster::rasterize_forward_kept(v, f, &cam)))
        .map_err(py_err)?;
    let (h, w) = (out.height, out.width);
    let state = RasterState {
        setup: T::keep(setup),
    };
    PyTuple::new(
        py,
        [
            array(py, out.tri_id, &[h, w])?.into_any().unbind(),
            array(py, out.bary, &[h, w, 2])?.into_any().unbind(),
            array(py, out.depth, &[h, w])?.into_any().unbind(),
            Py::new(py, state)?.into_any(),
        ],
    )
}

#[allow(clippy::too_many_arguments)]
fn rasterize_backward_typed<'py, T: KeptReal>(
    py: Python<'py>,
    state: Option<PyRef<'py, RasterState>>,
    verts: Arr<'py, T>,
    faces: Arr<'py, i32>,
    camera_args: CameraArgs,
    tri_id: Arr<'py, i32>,
    v_bary: Arr<'py, T>,
    num_threads: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<T>>> {
    let nv = shape_last(&verts, "verts", 2, 3, "(V, 3)")?[0];
    shape_last(&faces, "faces", 2, 3, "(F, 3) int32")?;
    image_dims(&tri_id, "tri_id", 2, "(H, W)")?;
    shape_last(&v_bary, "v_bary", 3, 2, "(H, W, 2)")?;
    let cam = camera(camera_args)?;
    let kept = match &state {
        None => None,
        Some(state) => Some(T::kept(&state.setup).ok_or_else(|| {
            InvalidArgumentError::new_err("state: kept by a forward of another float dtype than verts")
        })?),
    };
    let (v, f, t, g) = (
        data(&verts, "verts")?,
        data(&faces, "faces")?,
        data(&tri_id, "tri_id")?,
        data(&v_bary, "v_bary")?,
    );
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || match kept {
                Some(kept) => raster::rasterize_backward_kept(kept, v, f, &cam, t, g),
                None => raster::rasterize_backward(v, f, &cam, t, g),
            })
        })
        .map_err(py_err)?;
    array(py, out, &[nv, 3])
}

fn interpolate_forward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    attr: Arr<'py, T>,
    faces: Arr<'py, i32>,
    tri_id: Arr<'py, i32>,
    bary: Arr<'py, T>,
    pixels: Option<Arr<'py, i64>>,
    num_threads: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<T>>> {
    let c = shape(&attr, "attr", 2, "(V, C)")?[1];
    shape_last(&faces, "faces", 2, 3, "(F, 3) int32")?;
    let (h, w) = image_dims(&tri_id, "tri_id", 2, "(H, W)")?;
    shape_last(&bary, "bary", 3, 2, "(H, W, 2)")?;
    let out_dims = match &pixels {
        Some(p) => vec![shape(p, "pixels", 1, "(P,) int64")?[0], c],
        None => vec![h, w, c],
    };
    let (a, f, t, b) = (
        data(&attr, "attr")?,
        data(&faces, "faces")?,
        data(&tri_id, "tri_id")?,
        data(&bary, "bary")?,
    );
    let p = optional_data(&pixels, "pixels")?;
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                raster::interpolate_forward(a, c, f, t, b, h, w, p)
            })
        })
        .map_err(py_err)?;
    array(py, out, &out_dims)
}

#[allow(clippy::type_complexity)]
fn interpolate_backward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    attr: Arr<'py, T>,
    faces: Arr<'py, i32>,
    tri_id: Arr<'py, i32>,
    bary: Arr<'py, T>,
    pixels: Option<Arr<'py, i64>>,
    v_out: Arr<'py, T>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let s = shape(&attr, "attr", 2, "(V, C)")?;
    shape_last(&faces, "faces", 2, 3, "(F, 3) int32")?;
    let (h, w) = image_dims(&tri_id, "tri_id", 2, "(H, W)")?;
    shape_last(&bary, "bary", 3, 2, "(H, W, 2)")?;
    match &pixels {
        Some(p) => {
            shape(p, "pixels", 1, "(P,) int64")?;
            shape(&v_out, "v_out", 2, "(P, C)")?
        }
        None => shape(&v_out, "v_out", 3, "(H, W, C)")?,
    };
    let (a, f, t, b, g) = (
        data(&attr, "attr")?,
        data(&faces, "faces")?,
        data(&tri_id, "tri_id")?,
        data(&bary, "bary")?,
        data(&v_out, "v_out")?,
    );
    let p = optional_data(&pixels, "pixels")?;
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                raster::interpolate_backward(a, s[1], f, t, b, h, w, p, g, needs.0, needs.1)
            })
        })
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            optional(py, out.v_attr, &s)?,
            optional(py, out.v_bary, &[h, w, 2])?,
        ],
    )
}

fn texture_forward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    tex: Arr<'py, T>,
    uv: Arr<'py, T>,
    num_threads: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<T>>> {
    let s = shape(&tex, "tex", 3, "(Ht, Wt, C)")?;
    let n = shape_last(&uv, "uv", 2, 2, "(N, 2)")?[0];
    let (t, u) = (data(&tex, "tex")?, data(&uv, "uv")?);
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::texture_forward(t, s[0], s[1], s[2], u)))
        .map_err(py_err)?;
    array(py, out, &[n, s[2]])
}

fn texture_backward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    tex: Arr<'py, T>,
    uv: Arr<'py, T>,
    v_out: Arr<'py, T>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let s = shape(&tex, "tex", 3, "(Ht, Wt, C)")?;
    let n = shape_last(&uv, "uv", 2, 2, "(N, 2)")?[0];
    shape(&v_out, "v_out", 2, "(N, C)")?;
    let (t, u, g) = (data(&tex, "tex")?, data(&uv, "uv")?, data(&v_out, "v_out")?);
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                raster::texture_backward(t, s[0], s[1], s[2], u, g, needs.0, needs.1)
            })
        })
        .map_err(py_err)?;
    let (indices, values) = match out.v_tex {
        Some(sp) => (
            array(py, sp.indices, &[2, sp.nnz])?.into_any().unbind(),
            array(py, sp.values, &[sp.nnz, s[2]])?.into_any().unbind(),
        ),
        None => (py.None(), py.None()),
    };
    PyTuple::new(py, [indices, values, optional(py, out.v_uv, &[n, 2])?])
}

/// The borrowed arrays of an antialias call.
struct AntialiasArrays<'py, T: Element> {
    color: Arr<'py, T>,
    tri_id: Arr<'py, i32>,
    depth: Arr<'py, T>,
    verts: Arr<'py, T>,
    faces: Arr<'py, i32>,
    topology: Arr<'py, i32>,
}

impl<T: Element + Real> AntialiasArrays<'_, T> {
    fn inputs<'a>(&'a self, cam: &'a urhead_core::Camera) -> PyResult<(AntialiasInputs<'a, T>, Vec<usize>)> {
        let s = shape(&self.color, "color", 3, "(H, W, C)")?;
        image_dims(&self.tri_id, "tri_id", 2, "(H, W)")?;
        image_dims(&self.depth, "depth", 2, "(H, W)")?;
        shape_last(&self.verts, "verts", 2, 3, "(V, 3)")?;
        shape_last(&self.faces, "faces", 2, 3, "(F, 3) int32")?;
        shape_last(&self.topology, "topology", 2, 3, "(F, 3) int32")?;
        if s[0] != cam.height as usize || s[1] != cam.width as usize {
            return Err(ShapeError::new_err(format!(
                "color must be (H, W, C) with (H, W) = ({}, {}) of the camera, got {s:?}",
                cam.height, cam.width
            )));
        }
        Ok((
            AntialiasInputs {
                color: data(&self.color, "color")?,
                channels: s[2],
                tri_id: data(&self.tri_id, "tri_id")?,
                depth: data(&self.depth, "depth")?,
                verts: data(&self.verts, "verts")?,
                faces: data(&self.faces, "faces")?,
                topology: data(&self.topology, "topology")?,
                camera: cam,
            },
            s,
        ))
    }
}

fn antialias_forward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    arrays: AntialiasArrays<'py, T>,
    camera_args: CameraArgs,
    keep_blends: bool,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let cam = camera(camera_args)?;
    let (inputs, s) = arrays.inputs(&cam)?;
    let (out, blends) = py
        .allow_threads(|| with_threads(num_threads, || raster::antialias_forward_blends(&inputs)))
        .map_err(py_err)?;
    let blends = keep_blends.then(|| blends.packed());
    let rows = blends.as_ref().map_or(0, |b| b.len() / PACKED_BLEND);
    PyTuple::new(
        py,
        [
            array(py, out, &s)?.into_any().unbind(),
            optional(py, blends, &[rows, PACKED_BLEND])?,
        ],
    )
}

fn antialias_backward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    arrays: AntialiasArrays<'py, T>,
    camera_args: CameraArgs,
    v_out: Arr<'py, T>,
    blends: Option<Arr<'py, f64>>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let cam = camera(camera_args)?;
    let (inputs, s) = arrays.inputs(&cam)?;
    shape(&v_out, "v_out", 3, "(H, W, C)")?;
    let g = data(&v_out, "v_out")?;
    let blends = match &blends {
        Some(b) => {
            shape_last(b, "blends", 2, PACKED_BLEND, "(B, 10) float64")?;
            let pixels = inputs.tri_id.len();
            Some(
                SilhouetteBlends::from_packed(data(b, "blends")?, pixels, inputs.verts.len() / 3)
                    .map_err(py_err)?,
            )
        }
        None => None,
    };
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || match &blends {
                Some(b) => raster::antialias_backward_blends(&inputs, g, needs.0, needs.1, b),
                None => raster::antialias_backward(&inputs, g, needs.0, needs.1),
            })
        })
        .map_err(py_err)?;
    let nv = inputs.verts.len() / 3;
    PyTuple::new(
        py,
        [
            optional(py, out.v_color, &s)?,
            optional(py, out.v_verts, &[nv, 3])?,
        ],
    )
}

fn rasterize_uv_typed<'py, T: Element + Real>(
    py: Python<'py>,
    uv_coords: Arr<'py, T>,
    uv_faces: Arr<'py, i32>,
    height: usize,
    width: usize,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    shape_last(&uv_coords, "uv_coords", 2, 2, "(T, 2)")?;
    shape_last(&uv_faces, "uv_faces", 2, 3, "(F, 3) int32")?;
    let (u, f) = (data(&uv_coords, "uv_coords")?, data(&uv_faces, "uv_faces")?);
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::rasterize_uv(u, f, height, width)))
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            array(py, out.tri_id, &[height, width])?.into_any(),
            array(py, out.bary, &[height, width, 2])?.into_any(),
        ],
    )
}

/// Edge adjacency `(F, 3)` of `faces` for `antialias`.
#[pyfunction]
pub fn edge_topology<'py>(
    py: Python<'py>,
    faces: Arr<'py, i32>,
    num_verts: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<i32>>> {
    let nf = shape_last(&faces, "faces", 2, 3, "(F, 3) int32")?[0];
    let f = data(&faces, "faces")?;
    let out = py
        .allow_threads(|| raster::edge_topology(f, num_verts))
        .map_err(py_err)?;
    array(py, out, &[nf, 3])
}

/// rasterize → (tri_id (H, W) int32, bary (H, W, 2), depth (H, W), state): the state keeps
/// the triangles' setup for the backward.
#[pyfunction]
pub fn rasterize_forward<'py>(
    py: Python<'py>,
    verts: &Bound<'py, PyAny>,
    faces: Arr<'py, i32>,
    camera: CameraArgs,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(verts, T => rasterize_forward_typed::<T>(py, verts.extract()?, faces, camera, num_threads))
}

/// rasterize backward → v_verts (V, 3); with the forward's state (or None: set up again).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward<'py>(
    py: Python<'py>,
    state: Option<PyRef<'py, RasterState>>,
    verts: &Bound<'py, PyAny>,
    faces: Arr<'py, i32>,
    camera: CameraArgs,
    tri_id: Arr<'py, i32>,
    v_bary: &Bound<'py, PyAny>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(verts, T => rasterize_backward_typed::<T>(
        py,
        state,
        verts.extract()?,
        faces,
        camera,
        tri_id,
        v_bary.extract()?,
        num_threads,
    )
    .map(Bound::into_any))
}

/// interpolate → (H, W, C), or (P, C) at `pixels` (P,) int64 when not None.
#[pyfunction]
pub fn interpolate_forward<'py>(
    py: Python<'py>,
    attr: &Bound<'py, PyAny>,
    faces: Arr<'py, i32>,
    tri_id: Arr<'py, i32>,
    bary: &Bound<'py, PyAny>,
    pixels: Option<Arr<'py, i64>>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(attr, T => interpolate_forward_typed::<T>(
        py,
        attr.extract()?,
        faces,
        tri_id,
        bary.extract()?,
        pixels,
        num_threads,
    )
    .map(Bound::into_any))
}

/// interpolate backward → (v_attr, v_bary (H, W, 2)), None where not requested; `v_out` is
/// (P, C) when `pixels` is not None.
#[pyfunction]
pub fn interpolate_backward<'py>(
    py: Python<'py>,
    attr: &Bound<'py, PyAny>,
    faces: Arr<'py, i32>,
    tri_id: Arr<'py, i32>,
    bary: &Bound<'py, PyAny>,
    pixels: Option<Arr<'py, i64>>,
    v_out: &Bound<'py, PyAny>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(attr, T => interpolate_backward_typed::<T>(
        py,
        attr.extract()?,
        faces,
        tri_id,
        bary.extract()?,
        pixels,
        v_out.extract()?,
        needs,
        num_threads,
    ))
}

/// texture → (N, C).
#[pyfunction]
pub fn texture_forward<'py>(
    py: Python<'py>,
    tex: &Bound<'py, PyAny>,
    uv: &Bound<'py, PyAny>,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(tex, T => texture_forward_typed::<T>(py, tex.extract()?, uv.extract()?, num_threads)
        .map(Bound::into_any))
}

/// texture backward → (indices (2, K) int64, values (K, C), v_uv (N, 2)), None where not
/// requested.
#[pyfunction]
pub fn texture_backward<'py>(
    py: Python<'py>,
    tex: &Bound<'py, PyAny>,
    uv: &Bound<'py, PyAny>,
    v_out: &Bound<'py, PyAny>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(tex, T => texture_backward_typed::<T>(
        py,
        tex.extract()?,
        uv.extract()?,
        v_out.extract()?,
        needs,
        num_threads,
    ))
}

/// antialias → `(image (H, W, C), blends (B, 10) float64 or None)`: the blends (with
/// `keep_blends`) are the pixel pairs it blended, which its backward can take instead of
/// searching them again.
#[pyfunction]
pub fn antialias_forward<'py>(
    py: Python<'py>,
    color: &Bound<'py, PyAny>,
    tri_id: Arr<'py, i32>,
    depth: &Bound<'py, PyAny>,
    verts: &Bound<'py, PyAny>,
    faces: Arr<'py, i32>,
    topology: Arr<'py, i32>,
    camera: CameraArgs,
    keep_blends: bool,
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(color, T => {
        let arrays = AntialiasArrays::<T> {
            color: color.extract()?,
            tri_id,
            depth: depth.extract()?,
            verts: verts.extract()?,
            faces,
            topology,
        };
        antialias_forward_typed(py, arrays, camera, keep_blends, num_threads).map(Bound::into_any)
    })
}

/// antialias backward → (v_color, v_verts), None where not requested; `blends` from the
/// forward on the same inputs, or None to find them again.
#[pyfunction]
#[pyo3(signature = (color, tri_id, depth, verts, faces, topology, camera, v_out, blends, needs, num_threads))]
pub fn antialias_backward<'py>(
    py: Python<'py>,
    color: &Bound<'py, PyAny>,
    tri_id: Arr<'py, i32>,
    depth: &Bound<'py, PyAny>,
    verts: &Bound<'py, PyAny>,
    faces: Arr<'py, i32>,
    topology: Arr<'py, i32>,
    camera: CameraArgs,
    v_out: &Bound<'py, PyAny>,
    blends: Option<Arr<'py, f64>>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(color, T => {
        let arrays = AntialiasArrays::<T> {
            color: color.extract()?,
            tri_id,
            depth: depth.extract()?,
            verts: verts.extract()?,
            faces,
            topology,
        };
        antialias_backward_typed(py, arrays, camera, v_out.extract()?, blends, needs, num_threads)
    })
}

/// rasterize_uv → (tri_id (H, W) int32, bary (H, W, 2)).
#[pyfunction]
pub fn rasterize_uv<'py>(
    py: Python<'py>,
    uv_coords: &Bound<'py, PyAny>,
    uv_faces: Arr<'py, i32>,
    height: usize,
    width: usize,
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(uv_coords, T => rasterize_uv_typed::<T>(
        py,
        uv_coords.extract()?,
        uv_faces,
        height,
        width,
        num_threads,
    ))
}

fn scatter_pixels_forward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    values: Arr<'py, T>,
    pixels: Arr<'py, i64>,
    fill: Arr<'py, T>,
    background: Arr<'py, T>,
    (height, width): (usize, usize),
    num_threads: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<T>>> {
    shape(&values, "values", 2, "(P, C − K)")?;
    shape(&pixels, "pixels", 1, "(P,) int64")?;
    shape(&fill, "fill", 1, "(K,)")?;
    let c = shape(&background, "background", 1, "(C,)")?[0];
    let inputs = ScatterInputs {
        pixels: data(&pixels, "pixels")?,
        pixel_count: height * width,
        channels: c,
    };
    let (v, f, b) = (
        data(&values, "values")?,
        data(&fill, "fill")?,
        data(&background, "background")?,
    );
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::scatter_pixels_forward(&inputs, v, f, b)))
        .map_err(py_err)?;
    array(py, out, &[height, width, c])
}

fn scatter_pixels_backward_typed<'py, T: Element + Real>(
    py: Python<'py>,
    pixels: Arr<'py, i64>,
    v_image: Arr<'py, T>,
    fill: usize,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let p = shape(&pixels, "pixels", 1, "(P,) int64")?[0];
    let dims = shape(&v_image, "v_image", 3, "(H, W, C)")?;
    let inputs = ScatterInputs {
        pixels: data(&pixels, "pixels")?,
        pixel_count: dims[0] * dims[1],
        channels: dims[2],
    };
    let g = data(&v_image, "v_image")?;
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                raster::scatter_pixels_backward(&inputs, g, fill, needs.0, needs.1)
            })
        })
        .map_err(py_err)?;
    PyTuple::new(
        py,
        [
            optional(py, out.v_values, &[p, dims[2].saturating_sub(fill)])?,
            optional(py, out.v_background, &[dims[2]])?,
        ],
    )
}

/// The covered pixels of a rasterized `tri_id (H, W)`: (P,) int64 flat indices, increasing.
#[pyfunction]
pub fn covered_pixels<'py>(
    py: Python<'py>,
    tri_id: Arr<'py, i32>,
    num_threads: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<i64>>> {
    image_dims(&tri_id, "tri_id", 2, "(H, W)")?;
    let t = data(&tri_id, "tri_id")?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::covered_pixels(t)))
        .map_err(py_err)?;
    let n = out.len();
    array(py, out, &[n])
}

/// scatter_pixels → (H, W, C): `background (C,)` with `values (P, C − K)` then `fill (K,)`
/// at `pixels (P,)`.
#[pyfunction]
pub fn scatter_pixels_forward<'py>(
    py: Python<'py>,
    values: &Bound<'py, PyAny>,
    pixels: Arr<'py, i64>,
    fill: &Bound<'py, PyAny>,
    background: &Bound<'py, PyAny>,
    size: (usize, usize),
    num_threads: usize,
) -> PyResult<Bound<'py, PyAny>> {
    with_float_type!(values, T => scatter_pixels_forward_typed::<T>(
        py,
        values.extract()?,
        pixels,
        fill.extract()?,
        background.extract()?,
        size,
        num_threads,
    )
    .map(Bound::into_any))
}

/// scatter_pixels backward → (v_values (P, C − K), v_background (C,)), None where not
/// requested; `fill` is the forward's `K`.
#[pyfunction]
pub fn scatter_pixels_backward<'py>(
    py: Python<'py>,
    pixels: Arr<'py, i64>,
    v_image: &Bound<'py, PyAny>,
    fill: usize,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    with_float_type!(v_image, T => scatter_pixels_backward_typed::<T>(
        py,
        pixels,
        v_image.extract()?,
        fill,
        needs,
        num_threads,
    ))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RasterState>()?;
    m.add_function(wrap_pyfunction!(edge_topology, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_forward, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_backward, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate_forward, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate_backward, m)?)?;
    m.add_function(wrap_pyfunction!(texture_forward, m)?)?;
    m.add_function(wrap_pyfunction!(texture_backward, m)?)?;
    m.add_function(wrap_pyfunction!(antialias_forward, m)?)?;
    m.add_function(wrap_pyfunction!(antialias_backward, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_uv, m)?)?;
    m.add_function(wrap_pyfunction!(covered_pixels, m)?)?;
    m.add_function(wrap_pyfunction!(scatter_pixels_forward, m)?)?;
    m.add_function(wrap_pyfunction!(scatter_pixels_backward, m)?)?;
    Ok(())
}
