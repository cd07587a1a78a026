//! Binding of `urhead_core::raytrace`: one call builds the scene (or refits a kept BVH to
//! it) and renders it.

use std::sync::Mutex;

use numpy::PyReadonlyArrayDyn;
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use urhead_core::raytrace::{render, Light, RenderSettings, Scene, SceneInputs, Texture, TriangleBvh};

use crate::arrays::{array, data, optional_data, shape};
use crate::camera::{camera, CameraArgs};
use crate::errors::{py_err, ShapeError};
use crate::pool::with_threads;

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;

/// `(direction, color, angular_radius, ambient_up, ambient_down, up)`
pub type LightArgs = ([f32; 3], [f32; 3], f32, [f32; 3], [f32; 3], [f32; 3]);

/// A BVH kept between renders of a mesh whose topology never changes; each render that
/// is given it refits it to that render's vertices. Renders sharing one wait for each
/// other (the lock is taken with the GIL released).
#[pyclass(frozen, name = "TriangleBvh")]
pub struct PyTriangleBvh {
    bvh: Mutex<TriangleBvh>,
}

#[pymethods]
impl PyTriangleBvh {
    /// Builds the tree over `vertices` (V, 3) float32 and `faces` (F, 3) int32.
    #[new]
    fn new(py: Python<'_>, vertices: Arr<'_, f32>, faces: Arr<'_, i32>) -> PyResult<Self> {
        shape(&vertices, "vertices", 2, "(V, 3)")?;
        shape(&faces, "faces", 2, "(F, 3)")?;
        let (v, f) = (data(&vertices, "vertices")?, data(&faces, "faces")?);
        let bvh = py
            .allow_threads(|| TriangleBvh::from_mesh(v, f))
            .map_err(py_err)?;
        Ok(Self { bvh: Mutex::new(bvh) })
    }

    /// Number of triangles the tree was built over.
    #[getter]
    fn num_faces(&self) -> usize {
        self.lock().num_tris()
    }
}

impl PyTriangleBvh {
    fn lock(&self) -> std::sync::MutexGuard<'_, TriangleBvh> {
        // A panic while refitting cannot leave a tree that traverses wrongly: every refit
        // recomputes all bounds before they are used.
        self.bvh.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Renders a triangle scene → (rgb (H,W,3), alpha (H,W), normal (H,W,3), depth (H,W),
/// centre_face (H,W) int32, centre_bary (H,W,2), centre_t (H,W)); the last three are None
/// without `centre_hits`.
#[pyfunction]
pub fn raytrace_render<'py>(
    py: Python<'py>,
    vertices: Arr<'py, f32>,
    faces: Arr<'py, i32>,
    normals: Arr<'py, f32>,
    colors: Arr<'py, f32>,
    solid: Arr<'py, f32>,
    uvs: Option<Arr<'py, f32>>,
    texture: Option<Arr<'py, f32>>,
    face_material: Arr<'py, i32>,
    materials: Arr<'py, f32>,
    decals: Arr<'py, f32>,
    light: LightArgs,
    camera_args: CameraArgs,
    samples_per_side: u32,
    edge_samples_per_side: u32,
    shadows: bool,
    centre_hits: bool,
    background: [f32; 3],
    seed: u32,
    num_threads: usize,
    bvh: Option<Bound<'py, PyTriangleBvh>>,
) -> PyResult<Bound<'py, PyTuple>> {
    let cam = camera(camera_args)?;
    shape(&vertices, "vertices", 2, "(V, 3)")?;
    shape(&faces, "faces", 2, "(F, 3)")?;
    shape(&normals, "normals", 2, "(V, 3)")?;
    shape(&colors, "colors", 2, "(V, 3)")?;
    shape(&solid, "solid", 2, "(V, 3)")?;
    shape(&face_material, "face_material", 1, "(F,)")?;
    shape(&materials, "materials", 2, "(M, 8)")?;
    shape(&decals, "decals", 2, "(D, 12)")?;
    if let Some(u) = &uvs {
        shape(u, "uvs", 2, "(V, 2)")?;
    }
    let tex = match &texture {
        Some(t) => {
            let s = shape(t, "texture", 3, "(TH, TW, 3)")?;
            if s[2] != 3 {
                return Err(ShapeError::new_err(format!(
                    "texture must be (TH, TW, 3), got {s:?}"
                )));
            }
            Some(Texture {
                data: data(t, "texture")?,
                width: s[1],
                height: s[0],
            })
        }
        None => None,
    };
    let (direction, color, angular_radius, ambient_up, ambient_down, up) = light;
    let inputs = SceneInputs {
        vertices: data(&vertices, "vertices")?,
        faces: data(&faces, "faces")?,
        normals: data(&normals, "normals")?,
        colors: data(&colors, "colors")?,
        solid: data(&solid, "solid")?,
        uvs: optional_data(&uvs, "uvs")?,
        face_material: data(&face_material, "face_material")?,
        materials: data(&materials, "materials")?,
        decals: data(&decals, "decals")?,
        texture: tex,
        light: Light {
            direction,
            color,
            angular_radius,
            ambient_up,
            ambient_down,
            up,
        },
    };
    let settings = RenderSettings {
        samples_per_side,
        edge_samples_per_side,
        shadows,
        centre_hits,
        background,
        seed,
    };
    let kept = bvh.as_ref().map(|b| b.get());
    let out = py
        .allow_threads(|| {
            with_threads(num_threads, || match kept {
                Some(kept) => {
                    let mut tree = kept.lock();
                    render(&Scene::with_bvh(inputs, &mut tree)?, &cam, settings)
                }
                None => render(&Scene::new(inputs)?, &cam, settings),
            })
        })
        .map_err(py_err)?;
    let (h, w) = (cam.height as usize, cam.width as usize);
    let mut outputs = vec![
        array(py, out.rgb, &[h, w, 3])?.into_any(),
        array(py, out.alpha, &[h, w])?.into_any(),
        array(py, out.normal, &[h, w, 3])?.into_any(),
        array(py, out.depth, &[h, w])?.into_any(),
    ];
    if centre_hits {
        outputs.push(array(py, out.centre_face, &[h, w])?.into_any());
        outputs.push(array(py, out.centre_bary, &[h, w, 2])?.into_any());
        outputs.push(array(py, out.centre_t, &[h, w])?.into_any());
    } else {
        outputs.extend([
            py.None().into_bound(py),
            py.None().into_bound(py),
            py.None().into_bound(py),
        ]);
    }
    PyTuple::new(py, outputs)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(raytrace_render, m)?)?;
    m.add_class::<PyTriangleBvh>()?;
    Ok(())
}
