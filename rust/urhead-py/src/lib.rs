//! `urhead._core`: the thin binding of urhead-core. Each entry point validates its
//! arguments, releases the GIL, runs the core kernel on a pool of the requested size and
//! wraps the outputs as numpy arrays (zero-copy both ways). No math lives here.

mod adam;
mod arrays;
mod camera;
mod errors;
mod lbs;
mod memory;
mod pool;
mod raster;
mod raytrace;
mod shading;
mod splat;
mod ssim;

use pyo3::prelude::*;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("ShapeError", py.get_type::<errors::ShapeError>())?;
    m.add("NonFiniteError", py.get_type::<errors::NonFiniteError>())?;
    m.add("IndexRangeError", py.get_type::<errors::IndexRangeError>())?;
    m.add(
        "InvalidArgumentError",
        py.get_type::<errors::InvalidArgumentError>(),
    )?;
    m.add("SizeLimitError", py.get_type::<errors::SizeLimitError>())?;
    m.add_function(wrap_pyfunction!(camera::check_camera, m)?)?;
    m.add_function(wrap_pyfunction!(adam::sparse_adam_step, m)?)?;
    m.add_class::<adam::RowJournal>()?;
    m.add_function(wrap_pyfunction!(lbs::lbs_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(lbs::lbs_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(lbs::lbs_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(lbs::lbs_backward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(memory::huge_page_zeros_f32, m)?)?;
    m.add_function(wrap_pyfunction!(memory::huge_page_zeros_i32, m)?)?;
    raster::register(m)?;
    m.add_class::<splat::SplatState>()?;
    m.add_function(wrap_pyfunction!(splat::splat_project_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(splat::splat_project_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(splat::splat_rasterize_forward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(splat::splat_rasterize_backward_f32, m)?)?;
    m.add_function(wrap_pyfunction!(splat::splat_project_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(splat::splat_project_backward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(splat::splat_rasterize_forward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(splat::splat_rasterize_backward_f64, m)?)?;
    m.add_function(wrap_pyfunction!(raytrace::raytrace_render, m)?)?;
    m.add_class::<raytrace::PyTriangleBvh>()?;
    shading::register(m)?;
    ssim::register(m)?;
    Ok(())
}
