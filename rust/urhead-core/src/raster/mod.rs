//! Differentiable mesh rasterization in the style of nvdiffrast: small composable ops, each
//! with its forward and hand-written backward side by side.
//!
//! - [`rasterize`]: perspective rasterization of a triangle mesh → per-pixel triangle id,
//!   perspective-correct barycentrics of the triangle's 2nd and 3rd vertex, linear view
//!   depth. Backward: barycentric gradients → world-space vertex positions.
//! - [`interpolate`]: per-vertex attributes → per-pixel attributes through the barycentrics.
//! - [`texture`]: bilinear texture lookup; the texture gradient is a coalesced sparse
//!   (COO) list of the texels that received gradient.
//! - [`sh_texture`]: a texture lookup shaded with spherical harmonics in one pass, whose
//!   backward never reads the texture again.
//! - [`covered_pixels`], [`scatter_pixels_forward`]: the covered pixels as a list, and
//!   per-pixel rows back into an image over a background.
//! - [`antialias`]: analytic silhouette antialiasing with gradients to vertex positions.
//! - [`rasterize_uv`]: rasterization of the UV layout itself (per-texel triangle and
//!   barycentrics), no gradient.
//!
//! Conventions shared by every op:
//! - Pixel `(x, y)` is sampled at its centre `(x + 0.5, y + 0.5)`; images are row-major
//!   `(H, W, ...)` with row 0 at the top (OpenCV camera, y down).
//! - Coverage is watertight: clipped screen positions are snapped to
//!   1/2^[`SUBPIXEL_BITS`] px and tested with exact integer edge functions under the
//!   top-left rule, so a pixel centre on an edge shared by two triangles is covered by
//!   exactly one of them. Both facings are rasterized (no back-face culling).
//! - Triangles are clipped against the near plane `z = near` in camera space (and against
//!   a wide guard band around the viewport, which only bounds fixed-point coordinates);
//!   barycentrics always refer to the original, unclipped triangle. Pixels whose depth
//!   exceeds `far` are left empty.
//! - Depth test: the smaller linear depth wins; equal depth → the lower triangle id.
//! - Barycentrics are clamped to the simplex (a pixel inside the snapped triangle can sit a
//!   fraction of a sub-pixel step outside the exact one) and sum to 1.
//! - Parallelism is over fixed screen tiles (full-width bands of [`TILE_ROWS`] rows) and
//!   fixed chunks; gradients are reduced in a fixed order, so results are bitwise
//!   identical for any thread count.

mod antialias;
mod bins;
mod interpolate;
mod pixels;
mod rasterize;
mod runs;
mod setup;
mod sh_texture;
mod sparse;
mod taps;
mod texel;
mod texture;
mod topology;
mod uv;

pub use antialias::{
    antialias_backward, antialias_backward_blends, antialias_forward, antialias_forward_blends,
    AntialiasGrads, AntialiasInputs, SilhouetteBlends, PACKED_BLEND,
};
pub use interpolate::{interpolate_backward, interpolate_forward, InterpolateGrads};
pub use pixels::{
    covered_pixels, scatter_pixels_backward, scatter_pixels_forward, ScatterGrads, ScatterInputs,
};
pub use rasterize::{
    rasterize_backward, rasterize_backward_kept, rasterize_forward, rasterize_forward_kept, RasterSetup,
};
pub use setup::{GUARD_BAND_PX, SUBPIXEL_BITS};
pub use sh_texture::{
    sh_texture_backward, sh_texture_forward, ShTextureGradInputs, ShTextureGrads, ShTextureInputs,
    ShTextureOutput,
};
pub use sparse::{SparseTexels, TexelEntries, TextureSamples};
pub use texel::Texel;
pub use texture::{texture_backward, texture_forward, texture_gradient_entries, TextureGrads};
pub use topology::edge_topology;
pub use uv::rasterize_uv;

use crate::error::{check_indices, check_len, Error, Result};

/// Image rows per screen tile. Tiles span the full image width, so each is a contiguous
/// slice of every output image.
pub const TILE_ROWS: usize = 8;

/// Output of [`rasterize_forward`] and [`rasterize_uv`].
#[derive(Debug, Clone, PartialEq)]
pub struct RasterImage<T> {
    /// `(H, W)` triangle index, −1 where no triangle covers the pixel.
    pub tri_id: Vec<i32>,
    /// `(H, W, 2)` barycentrics of the triangle's 2nd and 3rd vertex (0 where empty); the
    /// 1st vertex's weight is 1 − b1 − b2.
    pub bary: Vec<T>,
    /// `(H, W)` linear view-space depth, +inf where empty (1 everywhere covered for UV).
    pub depth: Vec<T>,
    pub width: usize,
    pub height: usize,
}

/// Checks a `(F, 3)` face table against `num_verts` vertices; returns F.
pub(crate) fn check_faces(
    arg: &'static str,
    faces: &[i32],
    num_verts: usize,
    verts_arg: &str,
) -> Result<usize> {
    if faces.is_empty() || faces.len() % 3 != 0 {
        return Err(Error::Shape {
            arg,
            expected: "(F, 3) with F ≥ 1".into(),
            got: format!("{} elements", faces.len()),
        });
    }
    if num_verts == 0 {
        return Err(Error::Shape {
            arg: "verts",
            expected: format!("({verts_arg}, ...) with at least one vertex"),
            got: "0 vertices".into(),
        });
    }
    check_indices(arg, faces, 0, num_verts as i64)?;
    Ok(faces.len() / 3)
}

/// Checks a `(H, W)` triangle-id image against F faces.
pub(crate) fn check_tri_id(tri_id: &[i32], height: usize, width: usize, num_faces: usize) -> Result<()> {
    check_len(
        "tri_id",
        tri_id,
        height * width,
        &format!("(H, W) = ({height}, {width})"),
    )?;
    check_indices("tri_id", tri_id, -1, num_faces as i64)
}
