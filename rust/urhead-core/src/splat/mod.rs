//! Differentiable 3D Gaussian splatting with mesh-depth occlusion.
//!
//! The contract is gsplat's classic rasterization (DESIGN.md, NUMERICS.md): EWA projection
//! with the clamped Jacobian and a 0.3 px² dilation, an opacity-aware cut-off radius
//! min(3.33, √(2 ln(255·o)))·σ per axis, 16×16 tiles, a stable (tile, depth, index) order,
//! front-to-back compositing with α = min(0.99, o·exp(−σ)), samples with α < 1/255
//! skipped, a stop before T would fall below 1e-4, and T·background added last. The one
//! addition is the occlusion test of URHead: a sample whose Gaussian depth (view-space z
//! of its mean) exceeds `depth_map[pixel] + depth_eps` is skipped.
//!
//! Stages, each with its adjoint beside it:
//! - [`project_forward`] / [`project_backward`]: means, quats (wxyz), scales, opacities,
//!   optional SH → 2D means, conics, depths, radii, colours.
//! - [`rasterize_forward`] / [`rasterize_backward`]: 2D Gaussians → image and
//!   transmittance; the backward replays the forward's decisions exactly and reduces
//!   per-intersection gradient records per Gaussian in a fixed order (no float atomics;
//!   the same bits for any thread count).
//!
//! Shapes (row-major): `means (N,3)`, `quats (N,4)`, `scales (N,3)`, `opacities (N)`,
//! `sh (N,K,3)`, `means2d (N,2)`, `conics (N,3)` = (a, b, c) of [[a, b], [b, c]] = Σ₂⁻¹,
//! `depths (N)`, `radii (N,2)`, `colors (N,C)`, `image (H,W,C)`, `transmittance (H,W)`.

// Culls and thresholds are written `!(x >= limit)` on purpose: NaN must fail them
// (NUMERICS.md rule 1), which `x < limit` would not.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod binning;
pub mod lanes;
mod project;
mod raster;
mod raster_backward;
mod records;
#[cfg(any(test, feature = "testing"))]
pub mod synthetic;

pub use binning::Binning;
pub use project::{project_backward, project_forward};
pub use raster::{rasterize_forward, rasterize_forward_with, RasterForward};
pub use raster_backward::{rasterize_backward, rasterize_backward_with, RasterGrads};
#[cfg(any(test, feature = "testing"))]
pub use synthetic::SyntheticSplat;

use crate::error::{check_finite, check_len, Error, Result};
use crate::sh::num_sh_coeffs;
use crate::Real;

/// Samples with alpha below this are skipped; opacities below it are culled.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Alpha is clamped to this.
pub const ALPHA_MAX: f64 = 0.99;
/// Compositing stops before the transmittance would fall below this.
pub const T_STOP: f64 = 1e-4;
/// Added to the diagonal of every 2D covariance (px²).
pub const DILATION: f64 = 0.3;
/// Cap of the cut-off extent in standard deviations (≈ √(2 ln 255)).
pub const EXTENT_CAP: f64 = 3.33;
/// Tile side in pixels.
pub const TILE: usize = 16;
/// Largest accepted number of (tile, Gaussian) intersections. Each costs about 50 bytes
/// between binning and the backward's gradient records.
pub const MAX_INTERSECTIONS: usize = 1 << 26;
/// Gaussians per parallel work item in per-Gaussian passes (fixed: deterministic).
const GAUSSIAN_CHUNK: usize = 1024;

/// Spherical-harmonics colour coefficients `(N, K, 3)`, of which the first (degree+1)²
/// are used.
#[derive(Debug, Clone, Copy)]
pub struct ShCoeffs<'a, T> {
    pub coeffs: &'a [T],
    pub num_coeffs: usize,
    pub degree: usize,
}

impl<T> ShCoeffs<'_, T> {
    #[inline]
    fn of(&self, i: usize) -> &[T] {
        &self.coeffs[i * self.num_coeffs * 3..(i + 1) * self.num_coeffs * 3]
    }
}

/// The 3D Gaussians to project.
#[derive(Debug, Clone, Copy)]
pub struct ProjectInputs<'a, T> {
    pub means: &'a [T],
    /// Quaternions (w, x, y, z), normalised inside; zero ones are culled.
    pub quats: &'a [T],
    /// Standard deviations along the local axes (not log-scales).
    pub scales: &'a [T],
    pub opacities: &'a [T],
    /// Colours from SH evaluated for the view direction camera centre → mean, or none.
    pub sh: Option<ShCoeffs<'a, T>>,
    pub num_gaussians: usize,
}

impl<T: Real> ProjectInputs<'_, T> {
    fn validate(&self) -> Result<()> {
        let n = self.num_gaussians;
        check_len("means", self.means, n * 3, &format!("(N, 3) with N = {n}"))?;
        check_len("quats", self.quats, n * 4, &format!("(N, 4) with N = {n}"))?;
        check_len("scales", self.scales, n * 3, &format!("(N, 3) with N = {n}"))?;
        check_len("opacities", self.opacities, n, &format!("(N,) with N = {n}"))?;
        check_finite("means", self.means)?;
        check_finite("quats", self.quats)?;
        check_finite("scales", self.scales)?;
        check_finite("opacities", self.opacities)?;
        if let Some(sh) = self.sh {
            if sh.degree > 3 {
                return Err(Error::Invalid {
                    arg: "sh_degree",
                    reason: format!("must be 0, 1, 2 or 3, got {}", sh.degree),
                });
            }
            let need = num_sh_coeffs(sh.degree);
            if sh.num_coeffs < need {
                return Err(Error::Shape {
                    arg: "sh",
                    expected: format!("(N, K, 3) with K ≥ {need} for degree {}", sh.degree),
                    got: format!("K = {}", sh.num_coeffs),
                });
            }
            check_len(
                "sh",
                sh.coeffs,
                n * sh.num_coeffs * 3,
                &format!("(N, K, 3) with N = {n}"),
            )?;
            check_finite("sh", sh.coeffs)?;
        }
        Ok(())
    }

    #[inline]
    fn mean(&self, i: usize) -> [T; 3] {
        [self.means[i * 3], self.means[i * 3 + 1], self.means[i * 3 + 2]]
    }
    #[inline]
    fn quat(&self, i: usize) -> [T; 4] {
        std::array::from_fn(|k| self.quats[i * 4 + k])
    }
    #[inline]
    fn scale(&self, i: usize) -> [T; 3] {
        [self.scales[i * 3], self.scales[i * 3 + 1], self.scales[i * 3 + 2]]
    }
}

/// Outputs of [`project_forward`]. Culled Gaussians have radius (0, 0) and zeros elsewhere.
#[derive(Debug, Clone)]
pub struct Projected<T> {
    /// `(N, 2)` pixel coordinates of the projected means.
    pub means2d: Vec<T>,
    /// `(N, 3)` inverse of the dilated 2D covariance, (a, b, c).
    pub conics: Vec<T>,
    /// `(N,)` view-space z of the means.
    pub depths: Vec<T>,
    /// `(N, 2)` screen-space extent in pixels along x and y; 0 = culled.
    pub radii: Vec<i32>,
    /// `(N, 3)` colours from SH, when SH were given.
    pub colors: Option<Vec<T>>,
}

/// Gradients of the loss with respect to [`Projected`]; `None` means zero.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProjectGradOutputs<'a, T> {
    pub v_means2d: Option<&'a [T]>,
    pub v_conics: Option<&'a [T]>,
    pub v_colors: Option<&'a [T]>,
}

impl<T> ProjectGradOutputs<'_, T> {
    fn validate(&self, inputs: &ProjectInputs<T>) -> Result<()> {
        let n = inputs.num_gaussians;
        for (arg, g, row) in [
            ("v_means2d", self.v_means2d, 2),
            ("v_conics", self.v_conics, 3),
            ("v_colors", self.v_colors, 3),
        ] {
            if let Some(g) = g {
                check_len(arg, g, n * row, &format!("(N, {row}) with N = {n}"))?;
            }
        }
        Ok(())
    }
}

/// Which input gradients [`project_backward`] computes.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProjectNeeds {
    pub means: bool,
    pub quats: bool,
    pub scales: bool,
    pub sh: bool,
}

/// Input gradients of the projection; `Some` exactly where asked for.
#[derive(Debug, Clone, Default)]
pub struct ProjectGrads<T> {
    pub v_means: Option<Vec<T>>,
    pub v_quats: Option<Vec<T>>,
    pub v_scales: Option<Vec<T>>,
    /// `(N, K, 3)`; coefficients beyond the degree get zero.
    pub v_sh: Option<Vec<T>>,
}

/// What shows through the Gaussians: each pixel's colour gets `T·background` added.
#[derive(Debug, Clone, Copy)]
pub enum Background<'a, T> {
    /// `(C,)`: one colour at every pixel (finite).
    Uniform(&'a [T]),
    /// `(H, W, S)` with `S ≥ C`: an image behind the Gaussians, of which the first `C`
    /// channels show (the avatar's antialiased mesh as its RGBA, with no copy of the
    /// colour). Compositing over it here saves a pass over three images and a kernel
    /// call. Its values are data, as a composite's: a non-finite one passes into its pixel.
    Image { values: &'a [T], channels: usize },
}

/// The projected 2D Gaussians and per-pixel state the rasterizer takes.
#[derive(Debug, Clone, Copy)]
pub struct RasterInputs<'a, T> {
    pub means2d: &'a [T],
    pub conics: &'a [T],
    /// `(N, C)` any number of channels C ≥ 1.
    pub colors: &'a [T],
    pub opacities: &'a [T],
    pub depths: &'a [T],
    /// `(N, 2)`; Gaussians with a zero radius are skipped.
    pub radii: &'a [i32],
    pub num_gaussians: usize,
    pub channels: usize,
    pub width: usize,
    pub height: usize,
    /// What shows through the Gaussians, added as T·background; zero when `None`.
    pub background: Option<Background<'a, T>>,
    /// `(H, W)` linear view-space depth of the mesh; +inf where there is no surface.
    pub depth_map: Option<&'a [T]>,
    pub depth_eps: T,
}

impl<T: Real> RasterInputs<'_, T> {
    fn validate(&self) -> Result<()> {
        let (n, c) = (self.num_gaussians, self.channels);
        if c == 0 {
            return Err(Error::Shape {
                arg: "colors",
                expected: "(N, C) with C ≥ 1".into(),
                got: "C = 0".into(),
            });
        }
        if self.width == 0 || self.height == 0 {
            return Err(Error::Invalid {
                arg: "width",
                reason: format!("image must be non-empty, got {}×{}", self.width, self.height),
            });
        }
        check_len("means2d", self.means2d, n * 2, &format!("(N, 2) with N = {n}"))?;
        check_len("conics", self.conics, n * 3, &format!("(N, 3) with N = {n}"))?;
        check_len(
            "colors",
            self.colors,
            n * c,
            &format!("(N, C) with N = {n}, C = {c}"),
        )?;
        check_len("opacities", self.opacities, n, &format!("(N,) with N = {n}"))?;
        check_len("depths", self.depths, n, &format!("(N,) with N = {n}"))?;
        check_len("radii", self.radii, n * 2, &format!("(N, 2) with N = {n}"))?;
        crate::error::check_indices("radii", self.radii, 0, i32::MAX as i64)?;
        check_finite("means2d", self.means2d)?;
        check_finite("conics", self.conics)?;
        check_finite("colors", self.colors)?;
        check_finite("opacities", self.opacities)?;
        check_finite("depths", self.depths)?;
        match self.background {
            Some(Background::Uniform(bg)) => {
                check_len("background", bg, c, &format!("(C,) with C = {c}"))?;
                check_finite("background", bg)?;
            }
            Some(Background::Image { values, channels }) => {
                if channels < c {
                    return Err(Error::Shape {
                        arg: "background",
                        expected: format!("(H, W, S) with S ≥ C = {c}"),
                        got: format!("S = {channels}"),
                    });
                }
                let (w, h) = (self.width, self.height);
                check_len(
                    "background",
                    values,
                    w * h * channels,
                    &format!("(H, W, S) = ({h}, {w}, {channels})"),
                )?;
            }
            None => {}
        }
        if let Some(d) = self.depth_map {
            check_len(
                "depth_map",
                d,
                self.width * self.height,
                &format!("(H, W) = ({}, {})", self.height, self.width),
            )?;
            if let Some(index) = d.iter().position(|v| v.is_nan()) {
                return Err(Error::NonFinite {
                    arg: "depth_map",
                    index,
                    value: f64::NAN,
                });
            }
        }
        if !self.depth_eps.is_finite() {
            return Err(Error::Invalid {
                arg: "depth_eps",
                reason: format!("must be finite, got {:?}", self.depth_eps),
            });
        }
        Ok(())
    }
}

/// A float type the splatting kernels run in, with its fastest lane implementation.
pub trait SplatReal: Real + lanes::KernelExp {
    /// Lanes used by [`rasterize_forward`] / [`rasterize_backward`].
    type Fast: lanes::Lanes<Elem = Self>;
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
impl SplatReal for f32 {
    type Fast = lanes::Avx2;
}

#[cfg(not(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma")))]
impl SplatReal for f32 {
    type Fast = lanes::Emu<f32>;
}

impl SplatReal for f64 {
    type Fast = lanes::Emu<f64>;
}
