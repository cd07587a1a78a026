//! `urhead._core`: the thin binding of urhead-core. Each module registers its entry points
//! (`register`); an entry point converts its arguments, releases the GIL, runs the core
//! kernel on a pool of the requested size and wraps the outputs as numpy arrays (zero-copy
//! both ways). No math lives here. Python reaches this module only through
//! `urhead.ops._bridge`.
//!
//! Validation policy (the one statement of it; the other layers point here). Every check
//! lives in the lowest layer that can see what it checks, and runs before any work:
//! - the core (`urhead_core::error`) checks everything expressible on slices and sizes:
//!   lengths, agreement between arguments, index ranges, finiteness, size limits. It is
//!   the source of truth, and what `cargo test` exercises;
//! - this binding checks only what is lost when an array becomes a slice: the number of
//!   dimensions, and the sizes it then passes to the core;
//! - Python (`urhead.ops`) checks only what the binding cannot see: that an argument is a
//!   dense CPU torch tensor of the right dtype, contiguous, and differentiated only where
//!   the op allows; and shapes it needs itself before the call (to reshape or allocate).
//!
//! Each failure is a typed error naming the argument (`errors.rs` maps core errors to the
//! `urhead.errors` exceptions).

mod adam;
mod arrays;
mod camera;
mod composite;
mod errors;
mod lbs;
mod lift;
mod memory;
mod pool;
mod raster;
mod raytrace;
mod rotate;
mod sh_texture;
mod shading;
mod splat;
mod ssim;
mod uv_error;

use pyo3::prelude::*;

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::register(m)?;
    camera::register(m)?;
    composite::register(m)?;
    adam::register(m)?;
    lbs::register(m)?;
    lift::register(m)?;
    memory::register(m)?;
    raster::register(m)?;
    splat::register(m)?;
    raytrace::register(m)?;
    rotate::register(m)?;
    sh_texture::register(m)?;
    shading::register(m)?;
    ssim::register(m)?;
    uv_error::register(m)?;
    Ok(())
}
