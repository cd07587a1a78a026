//! Deterministic synthetic splatting scenes shared by tests and benches: Gaussians of
//! head-avatar size (a few mm) filling a head-sized ellipsoid in front of a camera.

use super::{Background, ProjectInputs, Projected, RasterInputs, ShCoeffs};
use crate::sh::num_sh_coeffs;
use crate::testing::Rng;
use crate::{Camera, Real};

/// Owned inputs of a random scene.
#[derive(Debug, Clone)]
pub struct SyntheticSplat<T> {
    pub means: Vec<T>,
    pub quats: Vec<T>,
    pub scales: Vec<T>,
    pub opacities: Vec<T>,
    /// `(N, 16, 3)` degree-3 SH coefficients.
    pub sh: Vec<T>,
    pub num_gaussians: usize,
    pub camera: Camera,
}

impl<T: Real> SyntheticSplat<T> {
    /// `n` Gaussians with log-uniform scales in [1, 5] mm, opacities in [0.1, 0.99], in an
    /// ellipsoid of semi-axes (8, 11, 10) cm centred `distance` metres in front of a
    /// `size`² camera whose image the head fills to about 70 %.
    pub fn head(n: usize, size: u32, distance: f64, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let mut means = Vec::with_capacity(n * 3);
        while means.len() < n * 3 {
            let p = [0, 1, 2].map(|_| rng.uniform(-1.0, 1.0));
            if p.iter().map(|v| v * v).sum::<f64>() <= 1.0 {
                means.extend([T::c(0.08 * p[0]), T::c(0.11 * p[1]), T::c(0.10 * p[2] + distance)]);
            }
        }
        let quats = (0..n * 4).map(|_| T::c(rng.uniform(-1.0, 1.0))).collect();
        let scales = (0..n * 3)
            .map(|_| T::c(1e-3 * 5f64.powf(rng.uniform(0.0, 1.0))))
            .collect();
        let opacities = rng.vec(n, 0.1, 0.99);
        let k = num_sh_coeffs(3);
        let sh = (0..n * k * 3)
            .map(|i| {
                T::c(if i % (k * 3) < 3 {
                    rng.uniform(-1.5, 1.5)
                } else {
                    rng.uniform(-0.2, 0.2)
                })
            })
            .collect();
        let focal = 0.7 * size as f64 * distance / 0.22;
        let half = size as f32 / 2.0;
        let eye = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let camera = Camera::new(
            [
                [focal as f32, 0.0, half],
                [0.0, focal as f32, half],
                [0.0, 0.0, 1.0],
            ],
            eye,
            size,
            size,
            0.01,
            100.0,
        )
        .expect("valid synthetic camera");
        Self {
            means,
            quats,
            scales,
            opacities,
            sh,
            num_gaussians: n,
            camera,
        }
    }

    /// Projection inputs with SH of `degree` (None: no colours from SH).
    pub fn inputs(&self, degree: Option<usize>) -> ProjectInputs<'_, T> {
        ProjectInputs {
            means: &self.means,
            quats: &self.quats,
            scales: &self.scales,
            opacities: &self.opacities,
            sh: degree.map(|degree| ShCoeffs {
                coeffs: &self.sh,
                num_coeffs: num_sh_coeffs(3),
                degree,
            }),
            num_gaussians: self.num_gaussians,
        }
    }

    /// Compositing inputs of the scene projected (`proj`, with colours) over the camera's
    /// image, with occlusion tolerance `depth_eps`.
    pub fn raster_inputs<'a>(
        &'a self,
        proj: &'a Projected<T>,
        background: Option<&'a [T]>,
        depth_map: Option<&'a [T]>,
        depth_eps: T,
    ) -> RasterInputs<'a, T> {
        RasterInputs {
            means2d: &proj.means2d,
            conics: &proj.conics,
            colors: proj.colors.as_deref().expect("projected with SH colours"),
            opacities: &self.opacities,
            depths: &proj.depths,
            radii: &proj.radii,
            num_gaussians: self.num_gaussians,
            channels: 3,
            width: self.camera.width as usize,
            height: self.camera.height as usize,
            background: background.map(Background::Uniform),
            depth_map,
            depth_eps,
        }
    }
}
