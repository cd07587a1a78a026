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
use super::l1::{add_slope_row, row_sum};
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
    let (ssim, _, grad) = ssim_and_l1_with_grad(inputs, weight, None)?;
    Ok((ssim, grad))
}

/// Masked mean SSIM and masked L1 ([`super::masked_l1`]) of the same images, and the
/// gradient of `ssim_weight · SSIM + l1_weight · L1` with respect to `image`: the 3DGS
/// photometric loss in the SSIM gradient's pass, which reads both images anyway — no pass
/// of the L1's own and no second gradient image to add. Returns `(SSIM, L1, gradient)`,
/// each value and the gradient bit for bit those of the two kernels apart (the gradient
/// the sum of theirs).
pub fn masked_ssim_l1_with_grad<T: Real>(
    inputs: &SsimInputs<'_, T>,
    ssim_weight: f64,
    l1_weight: f64,
) -> Result<(T, T, Vec<T>)> {
    check_weight(l1_weight)?;
    ssim_and_l1_with_grad(inputs, ssim_weight, Some(l1_weight))
}

/// SSIM with its gradient, and the L1 term's value and gradient folded in when
/// `l1_weight` is given (the L1's value is 0 otherwise).
fn ssim_and_l1_with_grad<T: Real>(
    inputs: &SsimInputs<'_, T>,
    weight: f64,
    l1_weight: Option<f64>,
) -> Result<(T, T, Vec<T>)> {
    check_weight(weight)?;
    let mask_sum = inputs.validate_same_channels()?;
    let channels = inputs.channels as f64;
    let norm = mask_sum.max(1.0);
    let l1_denominator = (mask_sum * channels).max(1.0); // as masked_l1's
    let (h, len) = (inputs.height, inputs.width * inputs.channels);
    let scale = T::c(weight / (norm * channels));
    let l1_scale = l1_weight.map(|w| T::c(w / l1_denominator));
    let mut grad = zeroed("SSIM gradient (H, W, C)", h * len)?;
    let partials: Vec<(f64, f64)> = grad
        .par_chunks_mut(BAND_ROWS * len)
        .zip(bands(h))
        .map(|(grad_band, (start, end))| band_with_grad(inputs, start, end, scale, l1_scale, grad_band))
        .collect();
    let ssim: f64 = partials.iter().map(|p| p.0).sum();
    let l1: f64 = partials.iter().map(|p| p.1).sum();
    Ok((T::c(ssim / (norm * channels)), T::c(l1 / l1_denominator), grad))
}

/// One band of rows `[start, end)`: returns its Σ m·SSIM and Σ m·|x − y| (0 without
/// `l1_scale`) and writes its gradient rows (with the L1's subgradient at `l1_scale`).
fn band_with_grad<T: Real>(
    inputs: &SsimInputs<'_, T>,
    start: usize,
    end: usize,
    scale: T,
    l1_scale: Option<T>,
    grad: &mut [T],
) -> (f64, f64) {
    let (h, len) = (inputs.height, inputs.width * inputs.channels);
    let half = WINDOW / 2;
    let weights_1d: [T; WINDOW] = gaussian_window();
    // Coefficient rows reach `half` rows beyond the band; their moments `half` more.
    let (first, last) = (start.saturating_sub(half), (end + half).min(h));
    // The coefficients are zero off `columns` of these rows (see `ssim_columns`), so their
    // blur, the gradient, is zero off those widened by the window.
    let mut moments = MomentStream::new(inputs, first, &inputs.ssim_columns(first..last));
    let (weighted, reached) = (moments.wanted(), moments.reach());
    // Zero outside `columns`, which the coefficients' horizontal pass reads as such.
    let mut coefficients = PaddedRows::<T, COEFFICIENTS>::new(inputs.width, inputs.channels);
    let mut ring = RowRing::new(h, COEFFICIENTS, len);
    let mut blurred = vec![T::zero(); COEFFICIENTS * len];
    // SSIM is exactly 1 off `columns`.
    let (mut mask, mut ssim) = (vec![T::zero(); len], vec![T::one(); len]);
    let mut output_mask = vec![T::zero(); if l1_scale.is_some() { len } else { 0 }];
    let mut next_output = start;
    let (mut total, mut l1_total) = (0.0, 0.0);
    for row in first..last {
        let m = moments.row(row);
        expand_mask_row(inputs, row, &mut mask);
        let [mu_x, mu_y, e_xx, e_yy, e_xy]: [&[T]; MOMENTS] =
            std::array::from_fn(|k| &m[k * len..(k + 1) * len]);
        let [ca, cb, cc] = coefficients.interiors_mut();
        for t in weighted.clone() {
            let terms = PixelTerms::new(mu_x[t], mu_y[t], e_xx[t], e_yy[t], e_xy[t]);
            let (a, b, c, s) = pixel_adjoint(&terms, mask[t] * scale);
            (ca[t], cb[t], cc[t], ssim[t]) = (a, b, c, s);
        }
        if (start..end).contains(&row) {
            total += dot(&ssim, &mask).to_f64().unwrap_or(f64::NAN);
        }
        coefficients.blur_into(&weights_1d, &reached, ring.slot_mut(row));
        // Gradient rows whose whole window of coefficient rows is now stored.
        while next_output < end && (next_output + half).min(h - 1) <= row {
            let r = next_output;
            ring.blur_column(r, &weights_1d, &reached, &mut blurred);
            let [ga, gb, gc]: [&[T]; COEFFICIENTS] =
                std::array::from_fn(|k| &blurred[k * len..(k + 1) * len]);
            let x = &inputs.image[r * len..(r + 1) * len];
            let y = &inputs.target[r * len..(r + 1) * len];
            let out = &mut grad[(r - start) * len..(r - start + 1) * len];
            for t in reached.clone() {
                out[t] = x[t].mul_add(gb[t], y[t].mul_add(gc[t], ga[t]));
            }
            if let Some(l1_scale) = l1_scale {
                expand_mask_row(inputs, r, &mut output_mask);
                l1_total += row_sum(x, y, &output_mask);
                add_slope_row(x, y, &output_mask, l1_scale, out);
            }
            next_output += 1;
        }
    }
    debug_assert_eq!(next_output, end);
    (total, l1_total)
}
