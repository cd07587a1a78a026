//! urhead-core: the CPU kernels of urhead, with forward and hand-written backward passes
//! side by side. No Python here: `cargo test` and `cargo bench` run on their own.
//!
//! Conventions (see DESIGN.md): OpenCV camera axes, row-major contiguous slices, gradients
//! named `v_<input>`, rayon parallelism over fixed-size chunks so results are bitwise
//! identical for any thread count (no float atomics, reductions merged in a fixed order).

pub mod adam;
pub mod camera;
pub mod composite;
pub mod error;
pub mod lbs;
pub mod lift;
pub mod lift_tail;
pub mod mat3;
pub mod memory;
pub mod parallel;
pub mod raster;
pub mod raytrace;
pub mod real;
pub mod rotate;
pub mod sh;
pub mod shading;
pub mod splat;
pub mod ssim;
/// Deterministic fixtures for tests and benches: `cfg(test)` or the `testing` feature
/// (which the crate's own integration tests and benches enable), never the binding.
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod uv_error;

pub use camera::Camera;
pub use error::{Error, Result};
pub use real::Real;
