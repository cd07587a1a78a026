//! `rasterize_uv`: the mesh rasterized in its UV layout (the layout is the screen), giving
//! each texel centre its triangle and barycentrics. Used to lift Gaussians from UV points
//! and to scatter image-space error into UV. No gradient.

use super::rasterize::scan_tiles;
use super::setup::{setup_triangles, Hom, Viewport};
use super::{check_faces, RasterImage};
use crate::camera::MAX_IMAGE_SIDE;
use crate::error::{check_finite, Error, Result};
use crate::Real;

/// Rasterizes `uv_faces (F, 3)` of `uv_coords (T, 2)` into a `(height, width)` texel grid
/// with the texture convention (u right, v up, texel row 0 at v = 1, texel centres at
/// `((c + 0.5)/W, 1 − (r + 0.5)/H)`). Barycentrics are affine in UV. Overlapping islands
/// resolve to the lower triangle id; `depth` is 1 on covered texels.
pub fn rasterize_uv<T: Real>(
    uv_coords: &[T],
    uv_faces: &[i32],
    height: usize,
    width: usize,
) -> Result<RasterImage<T>> {
    for (arg, side) in [("height", height), ("width", width)] {
        if side == 0 || side > MAX_IMAGE_SIDE as usize {
            return Err(Error::Invalid {
                arg,
                reason: format!("must be in [1, {MAX_IMAGE_SIDE}], got {side}"),
            });
        }
    }
    if uv_coords.len() % 2 != 0 {
        return Err(Error::Shape {
            arg: "uv_coords",
            expected: "(T, 2)".into(),
            got: format!("{} elements", uv_coords.len()),
        });
    }
    check_faces("uv_faces", uv_faces, uv_coords.len() / 2, "T")?;
    check_finite("uv_coords", uv_coords)?;
    let hom: Vec<Hom> = uv_coords
        .chunks_exact(2)
        .map(|uv| {
            let (u, v) = (
                uv[0].to_f64().unwrap_or(f64::NAN),
                uv[1].to_f64().unwrap_or(f64::NAN),
            );
            [u * width as f64, (1.0 - v) * height as f64, 1.0]
        })
        .collect();
    let vp = Viewport {
        width,
        height,
        near: 0.0,
    };
    let setup = setup_triangles::<T>(&hom, uv_faces, &vp);
    scan_tiles(&setup, &vp, T::infinity())
}
