//! Backward: d(masked mean SSIM)/d(image), fused with the forward.
//!
//! With moments μx = G·x, E[x²] = G·x², E[xy] = G·(x·y) (G the blur, self-adjoint since
//! the window is symmetric and zero padding is linear), the chain rule gives, per channel,
//!
//!   dL/dx = G·a + x ⊙ G·(2·∂S/∂E[x²]·g) + y ⊙ G·(∂S/∂E[xy]·g),   a = ∂S/∂μx·g,
//!
//! with g the pixel's weight in the masked mean. So the gradient costs three more blurred
//! maps. The coefficients need the forward's moments, which are already streaming, so one
//! call computes both: a band recomputes 5 halo rows of moments on either side instead of
//! writing five full-image moment maps to memory and reading them back.

use rayon::prelude::*;

use super::blur::{PaddedRows, RowRing};
use super::forward::{expand_mask_row, MomentStream, MOMENTS};
use super::{bands, check_weight, gaussian_window, PixelTerms, SsimInputs, BAND_ROWS, WINDOW};
use crate::error::Result;
use crate::memory::zeroed;
use crate::parallel::dot;
use crate::Real;

/// Coefficient maps of the adjoint: the blurred ones, a, b, c.
const COEFFICIENTS: usize = 3;

/// Adjoint coefficients `(a, b, c)` of one element with mean weight `g`, and its SSIM.
#[inline(always)]
fn pixel_adjoint<T: Real>(p: &PixelTerms<T>, g: T) -> (T, T, T, T) {
    let (inv_b1, inv_b2) = p.inverses();
    let inv = inv_b1 * inv_b2;
    let ssim = p.a1 * p.a2 * inv;
    let g2 = g + g;
    // ∂S/∂μx = 2μy(A2 − A1)/(B1·B2) + 2μx·S·(1/B2 − 1/B1)
    let a = g2 * (p.mu_y * (p.a2 - p.a1) * inv + p.mu_x * ssim * (inv_b2 - inv_b1));
    // 2·∂S/∂E[x²] = −2S/B2, ∂S/∂E[xy] = 2A1/(B1·B2)
    let b = -g2 * ssim * inv_b2;
    let c = g2 * p.a1 * inv;
    (a, b, c, ssim)
}

/// Masked mean SSIM and the gradient of `weight ·` it with respect to `image` (`(H, W, C)`);
/// the target and mask are constants. One fused pass; the weight (a loss term's) joins the
/// mean's normalisation in the per-pixel scale, so no pass over the gradient scales it.
pub fn masked_ssim_with_grad<T: Real>(inputs: &SsimInputs<'_, T>, weight: f64) -> Result<(T, Vec<T>)> {
    check_weight(weight)?;
    let norm = inputs.validate_same_channels()?.max(1.0);
    let (h, len) = (inputs.height, inputs.width * inputs.channels);
    let scale = T::c(weight / (norm * inputs.channels as f64));
    let mut grad = zeroed("SSIM gradient (H, W, C)", h * len)?;
    let partials: Vec<f64> = grad
        .par_chunks_mut(BAND_ROWS * len)
        .zip(bands(h))
        .map(|(grad_band, (start, end))| band_with_grad(inputs, start, end, scale, grad_band))
        .collect();
    let total: f64 = partials.iter().sum();
    Ok((T::c(total / (norm * inputs.channels as f64)), grad))
}

/// One band of rows `[start, end)`: returns its Σ m·SSIM and writes its gradient rows.
fn band_with_grad<T: Real>(
    inputs: &SsimInputs<'_, T>,
    start: usize,
    end: usize,
    scale: T,
    grad: &mut [T],
) -> f64 {
    let (h, len) = (inputs.height, inputs.width * inputs.channels);
    let half = WINDOW / 2;
    let weights_1d: [T; WINDOW] = gaussian_window();
    // Coefficient rows reach `half` rows beyond the band; their moments `half` more.
    let (first, last) = (start.saturating_sub(half), (end + half).min(h));
    let mut moments = MomentStream::new(inputs, first);
    let mut coefficients = PaddedRows::<T, COEFFICIENTS>::new(inputs.width, inputs.channels);
    let mut ring = RowRing::new(h, COEFFICIENTS * len);
    let mut blurred = vec![T::zero(); COEFFICIENTS * len];
    let (mut mask, mut ssim) = (vec![T::zero(); len], vec![T::zero(); len]);
    let mut next_output = start;
    let mut total = 0.0;
    for row in first..last {
        let m = moments.row(row);
        expand_mask_row(inputs, row, &mut mask);
        let [mu_x, mu_y, e_xx, e_yy, e_xy]: [&[T]; MOMENTS] =
            std::array::from_fn(|k| &m[k * len..(k + 1) * len]);
        let [ca, cb, cc] = coefficients.interiors_mut();
        for t in 0..len {
            let terms = PixelTerms::new(mu_x[t], mu_y[t], e_xx[t], e_yy[t], e_xy[t]);
            let (a, b, c, s) = pixel_adjoint(&terms, mask[t] * scale);
            (ca[t], cb[t], cc[t], ssim[t]) = (a, b, c, s);
        }
        if (start..end).contains(&row) {
            total += dot(&ssim, &mask).to_f64().unwrap_or(f64::NAN);
        }
        coefficients.blur_into(&weights_1d, ring.slot_mut(row));
        // Gradient rows whose whole window of coefficient rows is now stored.
        while next_output < end && (next_output + half).min(h - 1) <= row {
            let r = next_output;
            ring.blur_column(r, &weights_1d, &mut blurred);
            let [ga, gb, gc]: [&[T]; COEFFICIENTS] =
                std::array::from_fn(|k| &blurred[k * len..(k + 1) * len]);
            let x = &inputs.image[r * len..(r + 1) * len];
            let y = &inputs.target[r * len..(r + 1) * len];
            let out = &mut grad[(r - start) * len..(r - start + 1) * len];
            for t in 0..len {
                out[t] = x[t].mul_add(gb[t], y[t].mul_add(gc[t], ga[t]));
            }
            next_output += 1;
        }
    }
    debug_assert_eq!(next_output, end);
    total
}
