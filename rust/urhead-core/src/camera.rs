//! The pinhole camera every kernel takes: OpenCV axes (x right, y down, z forward),
//! intrinsics in pixels, a world→camera matrix, pixel centres at (x + 0.5, y + 0.5).

use crate::error::{Error, Result};
use crate::mat3::map3;

/// A validated pinhole camera. Construct with [`Camera::new`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// World→camera, row-major 4×4; the last row is (0, 0, 0, 1).
    pub viewmat: [[f32; 4]; 4],
    pub width: u32,
    pub height: u32,
    pub near: f32,
    pub far: f32,
}

/// Largest accepted image side; larger sizes are almost certainly a units mistake and
/// would allocate gigabytes of per-pixel state.
pub const MAX_IMAGE_SIDE: u32 = 16384;

impl Camera {
    /// Validates and builds a camera from `k` (3×3 row-major intrinsics) and `viewmat`
    /// (4×4 row-major world→camera).
    pub fn new(
        k: [[f32; 3]; 3],
        viewmat: [[f32; 4]; 4],
        width: u32,
        height: u32,
        near: f32,
        far: f32,
    ) -> Result<Self> {
        let invalid = |arg, reason: String| Err(Error::Invalid { arg, reason });
        if k.iter().flatten().any(|x| !x.is_finite()) {
            return invalid("K", format!("must be finite, got {k:?}"));
        }
        if viewmat.iter().flatten().any(|x| !x.is_finite()) {
            return invalid("viewmat", format!("must be finite, got {viewmat:?}"));
        }
        if !(k[0][0] > 0.0 && k[1][1] > 0.0) {
            return invalid(
                "K",
                format!(
                    "focal lengths K[0,0], K[1,1] must be > 0, got {}, {}",
                    k[0][0], k[1][1]
                ),
            );
        }
        if k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
            return invalid(
                "K",
                format!("must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {k:?}"),
            );
        }
        if k[0][1] != 0.0 {
            return invalid("K", format!("skew K[0,1] must be 0, got {}", k[0][1]));
        }
        if viewmat[3] != [0.0, 0.0, 0.0, 1.0] {
            return invalid(
                "viewmat",
                format!("last row must be (0, 0, 0, 1), got {:?}", viewmat[3]),
            );
        }
        for (arg, side) in [("width", width), ("height", height)] {
            if side == 0 || side > MAX_IMAGE_SIDE {
                return invalid(arg, format!("must be in [1, {MAX_IMAGE_SIDE}], got {side}"));
            }
        }
        if !(near > 0.0 && far > near && far.is_finite()) {
            return invalid(
                "near",
                format!("need 0 < near < far < inf, got near {near}, far {far}"),
            );
        }
        Ok(Self {
            fx: k[0][0],
            fy: k[1][1],
            cx: k[0][2],
            cy: k[1][2],
            viewmat,
            width,
            height,
            near,
            far,
        })
    }

    /// World point → camera-space point.
    #[inline]
    pub fn to_camera(&self, p: [f32; 3]) -> [f32; 3] {
        let m = &self.viewmat;
        map3(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3])
    }

    /// Camera-space point → pixel coordinates (pixel centres at +0.5).
    #[inline]
    pub fn project(&self, c: [f32; 3]) -> [f32; 2] {
        [self.fx * c[0] / c[2] + self.cx, self.fy * c[1] / c[2] + self.cy]
    }

    /// Number of pixels, as `usize`.
    pub fn num_pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const I4: [[f32; 4]; 4] = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    const K: [[f32; 3]; 3] = [[100.0, 0.0, 32.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]];

    #[test]
    fn projects_principal_point() {
        let cam = Camera::new(K, I4, 64, 64, 0.01, 100.0).unwrap();
        assert_eq!(cam.project(cam.to_camera([0.0, 0.0, 2.0])), [32.0, 32.0]);
    }

    #[test]
    fn rejects_bad_arguments_by_name() {
        let mut k = K;
        k[0][0] = f32::NAN;
        let err = Camera::new(k, I4, 64, 64, 0.01, 100.0).unwrap_err();
        assert!(matches!(err, Error::Invalid { arg: "K", .. }));
        let err = Camera::new(K, I4, 0, 64, 0.01, 100.0).unwrap_err();
        assert!(matches!(err, Error::Invalid { arg: "width", .. }));
        let err = Camera::new(K, I4, 64, 64, 0.0, 100.0).unwrap_err();
        assert!(matches!(err, Error::Invalid { arg: "near", .. }));
        let mut v = I4;
        v[3][0] = 1.0;
        let err = Camera::new(K, v, 64, 64, 0.01, 100.0).unwrap_err();
        assert!(matches!(err, Error::Invalid { arg: "viewmat", .. }));
    }
}
