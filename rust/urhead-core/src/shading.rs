//! Batched spherical-harmonics colour for many surface samples seen along known view
//! directions: `rgb = max(Σ_k b_k(dir)·c_k + 0.5, 0)` (3DGS constants, [`crate::sh`]),
//! forward and the adjoint to the coefficients. The directions are constants (no gradient):
//! the mesh branch and the Gaussian lift use fixed camera rays.
//!
//! Coefficients are read from rows of a wider table (`stride` channels per sample, the
//! colour in the first `3·(degree+1)²`), so a view of the packed UV-map samples needs no
//! copy; the gradient is returned in the same `stride` layout, zero outside the colour.

use rayon::prelude::*;

use crate::error::{check_finite, check_len, Error, Result};
use crate::mat3::map3;
use crate::memory::{assume_written, unwritten, write_zeros};
use crate::sh::{direction, num_sh_coeffs, sh_basis, sh_sum, sh_sum_adjoint, unclamped};
use crate::Real;

/// Samples per rayon task: enough work to amortise the task, fixed so any thread count
/// gives the same partition (each sample is independent anyway).
const CHUNK: usize = 2048;

/// The arguments shared by the forward and the backward.
#[derive(Clone, Copy)]
pub struct ShadingInputs<'a, T> {
    /// (P, stride) rows whose first 3·(degree+1)² entries are the coefficients (k-major).
    pub coeffs: &'a [T],
    /// (P, 3) unit view directions.
    pub dirs: &'a [T],
    pub stride: usize,
    pub degree: usize,
}

impl<T: Real> ShadingInputs<'_, T> {
    fn validate(&self) -> Result<usize> {
        if self.degree > 3 {
            return Err(Error::Invalid {
                arg: "degree",
                reason: format!("must be 0, 1, 2 or 3, got {}", self.degree),
            });
        }
        let width = 3 * num_sh_coeffs(self.degree);
        if self.stride < width {
            return Err(Error::Invalid {
                arg: "coeffs",
                reason: format!(
                    "rows of {} channels cannot hold {width} coefficients",
                    self.stride
                ),
            });
        }
        let count = self.dirs.len() / 3;
        check_len("dirs", self.dirs, count * 3, "(P, 3)")?;
        check_len("coeffs", self.coeffs, count * self.stride, "(P, stride)")?;
        check_finite("dirs", self.dirs)?;
        Ok(count)
    }

    fn raw(&self, i: usize, b: &[T; 16]) -> [T; 3] {
        let width = 3 * num_sh_coeffs(self.degree);
        sh_sum(
            b,
            &self.coeffs[i * self.stride..i * self.stride + width],
            T::c(0.5),
        )
    }

    fn dir(&self, i: usize) -> [T; 3] {
        direction(self.dirs, i)
    }
}

/// (P, 3) colours.
pub fn shade_forward<T: Real>(inputs: &ShadingInputs<'_, T>) -> Result<Vec<T>> {
    let count = inputs.validate()?;
    let mut out = vec![T::zero(); count * 3];
    out.par_chunks_mut(CHUNK * 3).enumerate().for_each(|(c, block)| {
        for (j, rgb) in block.chunks_exact_mut(3).enumerate() {
            let i = c * CHUNK + j;
            let (b, _) = sh_basis(inputs.degree, inputs.dir(i), false);
            let raw = inputs.raw(i, &b);
            for ch in 0..3 {
                // NaN-safe clamp: a NaN coefficient gives NaN, not 0.
                rgb[ch] = if raw[ch] < T::zero() { T::zero() } else { raw[ch] };
            }
        }
    });
    Ok(out)
}

/// The gradient of the rows' other channels, given by the caller: `values (P, width)`
/// for channels `start..start + width`, after the colour.
#[derive(Clone, Copy)]
pub struct RestGradient<'a, T> {
    pub values: &'a [T],
    pub start: usize,
    pub width: usize,
}

/// ∂L/∂coeffs (P, stride) from ∂L/∂rgb (P, 3); channels clamped at 0 pass no gradient,
/// entries past the colour are zero, or with `rest` zero plus its rows at its channels —
/// the whole rows' gradient when the other channels feed other ops, written in the same
/// pass (no second pass over `(P, stride)` to add them).
pub fn shade_backward<T: Real>(
    inputs: &ShadingInputs<'_, T>,
    v_rgb: &[T],
    rest: Option<RestGradient<'_, T>>,
) -> Result<Vec<T>> {
    let count = inputs.validate()?;
    check_len("v_rgb", v_rgb, count * 3, "(P, 3)")?;
    let stride = inputs.stride;
    let n = num_sh_coeffs(inputs.degree);
    if let Some(rest) = &rest {
        if rest.start < 3 * n || rest.start + rest.width > stride {
            return Err(Error::Invalid {
                arg: "rest",
                reason: format!(
                    "channels {}..{} must lie after the colour's {} and within the rows' {stride}",
                    rest.start,
                    rest.start + rest.width,
                    3 * n
                ),
            });
        }
        check_len("rest", rest.values, count * rest.width, "(P, width)")?;
    }
    // Every row written whole on the pool: neither a serial memset of a reused heap block
    // (5.4 MB for 24k Gaussians' rows) nor a zeroing pass before the rows are written.
    let mut v_coeffs = unwritten("SH coefficient gradient (P, stride)", count * stride)?;
    v_coeffs
        .par_chunks_mut(CHUNK * stride)
        .enumerate()
        .for_each(|(c, block)| {
            for (j, row) in block.chunks_exact_mut(stride).enumerate() {
                let i = c * CHUNK + j;
                let (b, _) = sh_basis(inputs.degree, inputs.dir(i), false);
                let v = unclamped(inputs.raw(i, &b), map3(|ch| v_rgb[3 * i + ch]));
                sh_sum_adjoint(&b, v, &mut row[..3 * n]);
                write_zeros(&mut row[3 * n..]);
                if let Some(rest) = &rest {
                    let given = &rest.values[i * rest.width..(i + 1) * rest.width];
                    for (out, &g) in row[rest.start..rest.start + rest.width].iter_mut().zip(given) {
                        // Added to the zero entry, as autograd's sum would be (−0 becomes +0).
                        out.write(T::zero() + g);
                    }
                }
            }
        });
    // SAFETY: the blocks partition the rows, and every row was written whole above (the
    // colour's coefficients, then zeros over the rest).
    Ok(unsafe { assume_written(v_coeffs) })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sh::{sh_to_rgb, sh_to_rgb_backward};
    use crate::testing::Rng;

    fn case(count: usize, stride: usize) -> (Vec<f64>, Vec<f64>) {
        let mut rng = Rng::new(7);
        let coeffs: Vec<f64> = (0..count * stride).map(|_| rng.uniform(-0.8, 0.8)).collect();
        let mut dirs = Vec::new();
        for _ in 0..count {
            let d = [
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            ];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            dirs.extend(d.map(|x| x / len));
        }
        (coeffs, dirs)
    }

    #[test]
    fn matches_the_per_sample_functions() {
        for degree in 0..=3 {
            let stride = 3 * num_sh_coeffs(degree) + 5;
            let (coeffs, dirs) = case(5000, stride);
            let inputs = ShadingInputs {
                coeffs: &coeffs,
                dirs: &dirs,
                stride,
                degree,
            };
            let rgb = shade_forward(&inputs).unwrap();
            let mut rng = Rng::new(3);
            let v_rgb: Vec<f64> = (0..rgb.len()).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let v = shade_backward(&inputs, &v_rgb, None).unwrap();
            for i in 0..5000 {
                let d = [dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]];
                let row = &coeffs[i * stride..(i + 1) * stride];
                assert_eq!(
                    sh_to_rgb(degree, d, row),
                    [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]]
                );
                let mut expected = vec![0.0; stride];
                let g = [v_rgb[3 * i], v_rgb[3 * i + 1], v_rgb[3 * i + 2]];
                sh_to_rgb_backward(degree, d, row, g, Some(&mut expected));
                assert_eq!(&v[i * stride..(i + 1) * stride], &expected[..]);
            }
        }
    }

    #[test]
    fn rejects_bad_arguments() {
        let (coeffs, dirs) = case(4, 48);
        let ok = ShadingInputs {
            coeffs: &coeffs,
            dirs: &dirs,
            stride: 48,
            degree: 3,
        };
        assert!(shade_forward(&ok).is_ok());
        assert!(shade_forward(&ShadingInputs { degree: 4, ..ok }).is_err());
        assert!(shade_forward(&ShadingInputs { stride: 47, ..ok }).is_err());
        assert!(shade_forward(&ShadingInputs {
            coeffs: &coeffs[1..],
            ..ok
        })
        .is_err());
        let mut bad = dirs.clone();
        bad[4] = f64::NAN;
        assert!(shade_forward(&ShadingInputs { dirs: &bad, ..ok }).is_err());
        assert!(shade_backward(&ok, &[0.0; 11], None).is_err());
        let rest = |start, width, values: &'static [f64]| Some(RestGradient { values, start, width });
        let v_rgb = [0.0; 12];
        // Within the colour, past the rows, or the wrong length.
        assert!(shade_backward(&ShadingInputs { degree: 1, ..ok }, &v_rgb, rest(11, 1, &[0.0; 4])).is_err());
        assert!(shade_backward(&ShadingInputs { degree: 1, ..ok }, &v_rgb, rest(47, 2, &[0.0; 8])).is_err());
        assert!(shade_backward(&ShadingInputs { degree: 1, ..ok }, &v_rgb, rest(40, 2, &[0.0; 7])).is_err());
    }

    /// The other channels' gradient lands at its channels, added to zero (−0 becomes +0),
    /// and nothing else changes.
    #[test]
    fn the_rest_of_the_rows_gradient_is_written_in_place() {
        let (count, stride, degree) = (3000, 48 + 8, 2);
        let (coeffs, dirs) = case(count, stride);
        let inputs = ShadingInputs {
            coeffs: &coeffs,
            dirs: &dirs,
            stride,
            degree,
        };
        let mut rng = Rng::new(5);
        let v_rgb: Vec<f64> = (0..count * 3).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let (start, width) = (48, 6);
        let mut values: Vec<f64> = (0..count * width).map(|_| rng.uniform(-1.0, 1.0)).collect();
        values[7] = -0.0;
        let rest = RestGradient {
            values: &values,
            start,
            width,
        };
        let plain = shade_backward(&inputs, &v_rgb, None).unwrap();
        let with_rest = shade_backward(&inputs, &v_rgb, Some(rest)).unwrap();
        for i in 0..count {
            let (a, b) = (
                &plain[i * stride..(i + 1) * stride],
                &with_rest[i * stride..(i + 1) * stride],
            );
            for ch in 0..stride {
                let expected = match ch.checked_sub(start) {
                    Some(k) if k < width => 0.0 + values[i * width + k],
                    _ => a[ch],
                };
                assert_eq!(b[ch].to_bits(), expected.to_bits(), "sample {i} channel {ch}");
            }
        }
        // values[7] is sample 1's second channel: −0 written as +0.
        assert_eq!(with_rest[stride + start + 1].to_bits(), 0.0f64.to_bits());
    }
}
