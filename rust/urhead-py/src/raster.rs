//! Binding of `urhead_core::raster`: float32 and float64 entry points sharing generic
//! bodies. Each validates shapes, releases the GIL and runs the core on the requested pool.

use numpy::{Element, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::raster::{self, AntialiasInputs};
use urhead_core::Real;

use crate::arrays::{array, data, shape};
use crate::camera::{camera, CameraArgs};
use crate::errors::{py_err, ShapeError};
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

fn optional<'py, T: Element>(py: Python<'py>, x: Option<Vec<T>>, dims: &[usize]) -> PyResult<PyObject> {
    Ok(match x {
        Some(x) => array(py, x, dims)?.into_any().unbind(),
        None => py.None(),
    })
}

fn rasterize_forward<'py, T: Element + Real>(
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
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::rasterize_forward(v, f, &cam)))
        .map_err(py_err)?;
    let (h, w) = (out.height, out.width);
    PyTuple::new(
        py,
        [
            array(py, out.tri_id, &[h, w])?.into_any(),
            array(py, out.bary, &[h, w, 2])?.into_any(),
            array(py, out.depth, &[h, w])?.into_any(),
        ],
    )
}

fn rasterize_backward<'py, T: Element + Real>(
    py: Python<'py>,
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
    let (v, f, t, g) = (
        data(&verts, "verts")?,
        data(&faces, "faces")?,
        data(&tri_id, "tri_id")?,
        data(&v_bary, "v_bary")?,
    );
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::rasterize_backward(v, f, &cam, t, g)))
        .map_err(py_err)?;
    array(py, out, &[nv, 3])
}

fn interpolate_forward<'py, T: Element + Real>(
    py: Python<'py>,
    attr: Arr<'py, T>,
    faces: Arr<'py, i32>,
    tri_id: Arr<'py, i32>,
    bary: Arr<'py, T>,
    num_threads: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<T>>> {
    let c = shape(&attr, "attr", 2, "(V, C)")?[1];
    shape_last(&faces, "faces", 2, 3, "(F, 3) int32")?;
    let (h, w) = image_dims(&tri_id, "tri_id", 2, "(H, W)")?;
    shape_last(&bary, "bary", 3, 2, "(H, W, 2)")?;
    let (a, f, t, b) = (
        data(&attr, "attr")?,
        data(&faces, "faces")?,
        data(&tri_id, "tri_id")?,
        data(&bary, "bary")?,
    );
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::interpolate_forward(a, c, f, t, b, h, w)))
        .map_err(py_err)?;
    array(py, out, &[h, w, c])
}

#[allow(clippy::type_complexity)]
fn interpolate_backward<'py, T: Element + Real>(
    py: Python<'py>,
    attr: Arr<'py, T>,
    faces: Arr<'py, i32>,
    tri_id: Arr<'py, i32>,
    bary: Arr<'py, T>,
    v_out: Arr<'py, T>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let s = shape(&attr, "attr", 2, "(V, C)")?;
    shape_last(&faces, "faces", 2, 3, "(F, 3) int32")?;
    let (h, w) = image_dims(&tri_id, "tri_id", 2, "(H, W)")?;
    shape_last(&bary, "bary", 3, 2, "(H, W, 2)")?;
    shape(&v_out, "v_out", 3, "(H, W, C)")?;
    let (a, f, t, b, g) = (
        data(&attr, "attr")?,
        data(&faces, "faces")?,
        data(&tri_id, "tri_id")?,
        data(&bary, "bary")?,
        data(&v_out, "v_out")?,
    );
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                raster::interpolate_backward(a, s[1], f, t, b, h, w, g, needs.0, needs.1)
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

fn texture_forward<'py, T: Element + Real>(
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

fn texture_backward<'py, T: Element + Real>(
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

fn antialias_forward<'py, T: Element + Real>(
    py: Python<'py>,
    arrays: AntialiasArrays<'py, T>,
    camera_args: CameraArgs,
    num_threads: usize,
) -> PyResult<Bound<'py, numpy::PyArrayDyn<T>>> {
    let cam = camera(camera_args)?;
    let (inputs, s) = arrays.inputs(&cam)?;
    let out = py
        .allow_threads(|| with_threads(num_threads, || raster::antialias_forward(&inputs)))
        .map_err(py_err)?;
    array(py, out, &s)
}

fn antialias_backward<'py, T: Element + Real>(
    py: Python<'py>,
    arrays: AntialiasArrays<'py, T>,
    camera_args: CameraArgs,
    v_out: Arr<'py, T>,
    needs: (bool, bool),
    num_threads: usize,
) -> PyResult<Bound<'py, PyTuple>> {
    let cam = camera(camera_args)?;
    let (inputs, s) = arrays.inputs(&cam)?;
    shape(&v_out, "v_out", 3, "(H, W, C)")?;
    let g = data(&v_out, "v_out")?;
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || {
                raster::antialias_backward(&inputs, g, needs.0, needs.1)
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

fn rasterize_uv<'py, T: Element + Real>(
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

macro_rules! raster_entry_points {
    ($t:ty, $rf:ident, $rb:ident, $if_:ident, $ib:ident, $tf:ident, $tb:ident, $af:ident, $ab:ident, $uv:ident) => {
        /// rasterize → (tri_id (H, W) int32, bary (H, W, 2), depth (H, W)).
        #[pyfunction]
        pub fn $rf<'py>(
            py: Python<'py>,
            verts: Arr<'py, $t>,
            faces: Arr<'py, i32>,
            camera: CameraArgs,
            num_threads: usize,
        ) -> PyResult<Bound<'py, PyTuple>> {
            rasterize_forward(py, verts, faces, camera, num_threads)
        }

        /// rasterize backward → v_verts (V, 3).
        #[pyfunction]
        pub fn $rb<'py>(
            py: Python<'py>,
            verts: Arr<'py, $t>,
            faces: Arr<'py, i32>,
            camera: CameraArgs,
            tri_id: Arr<'py, i32>,
            v_bary: Arr<'py, $t>,
            num_threads: usize,
        ) -> PyResult<Bound<'py, numpy::PyArrayDyn<$t>>> {
            rasterize_backward(py, verts, faces, camera, tri_id, v_bary, num_threads)
        }

        /// interpolate → (H, W, C).
        #[pyfunction]
        pub fn $if_<'py>(
            py: Python<'py>,
            attr: Arr<'py, $t>,
            faces: Arr<'py, i32>,
            tri_id: Arr<'py, i32>,
            bary: Arr<'py, $t>,
            num_threads: usize,
        ) -> PyResult<Bound<'py, numpy::PyArrayDyn<$t>>> {
            interpolate_forward(py, attr, faces, tri_id, bary, num_threads)
        }

        /// interpolate backward → (v_attr, v_bary), None where not requested.
        #[pyfunction]
        pub fn $ib<'py>(
            py: Python<'py>,
            attr: Arr<'py, $t>,
            faces: Arr<'py, i32>,
            tri_id: Arr<'py, i32>,
            bary: Arr<'py, $t>,
            v_out: Arr<'py, $t>,
            needs: (bool, bool),
            num_threads: usize,
        ) -> PyResult<Bound<'py, PyTuple>> {
            interpolate_backward(py, attr, faces, tri_id, bary, v_out, needs, num_threads)
        }

        /// texture → (N, C).
        #[pyfunction]
        pub fn $tf<'py>(
            py: Python<'py>,
            tex: Arr<'py, $t>,
            uv: Arr<'py, $t>,
            num_threads: usize,
        ) -> PyResult<Bound<'py, numpy::PyArrayDyn<$t>>> {
            texture_forward(py, tex, uv, num_threads)
        }

        /// texture backward → (indices (2, K) int64, values (K, C), v_uv (N, 2)), None
        /// where not requested.
        #[pyfunction]
        pub fn $tb<'py>(
            py: Python<'py>,
            tex: Arr<'py, $t>,
            uv: Arr<'py, $t>,
            v_out: Arr<'py, $t>,
            needs: (bool, bool),
            num_threads: usize,
        ) -> PyResult<Bound<'py, PyTuple>> {
            texture_backward(py, tex, uv, v_out, needs, num_threads)
        }

        /// antialias → (H, W, C).
        #[pyfunction]
        pub fn $af<'py>(
            py: Python<'py>,
            color: Arr<'py, $t>,
            tri_id: Arr<'py, i32>,
            depth: Arr<'py, $t>,
            verts: Arr<'py, $t>,
            faces: Arr<'py, i32>,
            topology: Arr<'py, i32>,
            camera: CameraArgs,
            num_threads: usize,
        ) -> PyResult<Bound<'py, numpy::PyArrayDyn<$t>>> {
            let arrays = AntialiasArrays {
                color,
                tri_id,
                depth,
                verts,
                faces,
                topology,
            };
            antialias_forward(py, arrays, camera, num_threads)
        }

        /// antialias backward → (v_color, v_verts), None where not requested.
        #[pyfunction]
        pub fn $ab<'py>(
            py: Python<'py>,
            color: Arr<'py, $t>,
            tri_id: Arr<'py, i32>,
            depth: Arr<'py, $t>,
            verts: Arr<'py, $t>,
            faces: Arr<'py, i32>,
            topology: Arr<'py, i32>,
            camera: CameraArgs,
            v_out: Arr<'py, $t>,
            needs: (bool, bool),
            num_threads: usize,
        ) -> PyResult<Bound<'py, PyTuple>> {
            let arrays = AntialiasArrays {
                color,
                tri_id,
                depth,
                verts,
                faces,
                topology,
            };
            antialias_backward(py, arrays, camera, v_out, needs, num_threads)
        }

        /// rasterize_uv → (tri_id (H, W) int32, bary (H, W, 2)).
        #[pyfunction]
        pub fn $uv<'py>(
            py: Python<'py>,
            uv_coords: Arr<'py, $t>,
            uv_faces: Arr<'py, i32>,
            height: usize,
            width: usize,
            num_threads: usize,
        ) -> PyResult<Bound<'py, PyTuple>> {
            rasterize_uv(py, uv_coords, uv_faces, height, width, num_threads)
        }
    };
}

raster_entry_points!(
    f32,
    rasterize_forward_f32,
    rasterize_backward_f32,
    interpolate_forward_f32,
    interpolate_backward_f32,
    texture_forward_f32,
    texture_backward_f32,
    antialias_forward_f32,
    antialias_backward_f32,
    rasterize_uv_f32
);
raster_entry_points!(
    f64,
    rasterize_forward_f64,
    rasterize_backward_f64,
    interpolate_forward_f64,
    interpolate_backward_f64,
    texture_forward_f64,
    texture_backward_f64,
    antialias_forward_f64,
    antialias_backward_f64,
    rasterize_uv_f64
);

/// Registers the raster entry points on the extension module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(edge_topology, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(texture_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(texture_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(antialias_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(antialias_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_uv_f32, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_backward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate_backward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(texture_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(texture_backward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(antialias_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(antialias_backward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_uv_f64, m)?)?;
    Ok(())
}
