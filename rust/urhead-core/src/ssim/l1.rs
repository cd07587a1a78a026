//! Masked L1 `Σ_p m_p·Σ_c |x − y| / max(C·Σ_p m_p, 1)` and its subgradient (sign(0) = 0):
//! one pass over the images instead of torch's chain of elementwise kernels.

use rayon::prelude::*;

use super::forward::expand_mask_row;
use super::{SsimInputs, BAND_ROWS};
use crate::error::Result;
use crate::memory::zeroed;
use crate::Real;

/// Masked mean absolute difference.
pub fn masked_l1<T: Real>(inputs: &SsimInputs<'_, T>) -> Result<T> {
    let norm = inputs.validate()?;
    let len = inputs.width * inputs.channels;
    let partials: Vec<f64> = inputs
        .image
        .par_chunks(BAND_ROWS * len)
        .zip(inputs.target.par_chunks(BAND_ROWS * len))
        .enumerate()
        .map(|(band, (x, y))| {
            let mut mask = vec![T::zero(); len];
            let mut total = 0.0;
            for (i, (x, y)) in x.chunks_exact(len).zip(y.chunks_exact(len)).enumerate() {
                expand_mask_row(inputs, band * BAND_ROWS + i, &mut mask);
                total += row_sum(x, y, &mask);
            }
            total
        })
        .collect();
    let denominator = (norm * inputs.channels as f64).max(1.0);
    Ok(T::c(partials.iter().sum::<f64>() / denominator))
}

/// Masked mean absolute difference and its subgradient with respect to `image`.
pub fn masked_l1_with_grad<T: Real>(inputs: &SsimInputs<'_, T>) -> Result<(T, Vec<T>)> {
    let norm = inputs.validate()?;
    let len = inputs.width * inputs.channels;
    let denominator = (norm * inputs.channels as f64).max(1.0);
    let scale = T::c(1.0 / denominator);
    let mut grad = zeroed("L1 gradient (H, W, C)", inputs.height * len)?;
    let partials: Vec<f64> = grad
        .par_chunks_mut(BAND_ROWS * len)
        .zip(inputs.image.par_chunks(BAND_ROWS * len))
        .zip(inputs.target.par_chunks(BAND_ROWS * len))
        .enumerate()
        .map(|(band, ((grad, x), y))| {
            let mut mask = vec![T::zero(); len];
            let mut total = 0.0;
            let rows = grad
                .chunks_exact_mut(len)
                .zip(x.chunks_exact(len))
                .zip(y.chunks_exact(len));
            for (i, ((g, x), y)) in rows.enumerate() {
                expand_mask_row(inputs, band * BAND_ROWS + i, &mut mask);
                total += row_sum(x, y, &mask);
                for t in 0..len {
                    let d = x[t] - y[t];
                    let sign = if d > T::zero() {
                        T::one()
                    } else if d < T::zero() {
                        -T::one()
                    } else {
                        T::zero()
                    };
                    g[t] = mask[t] * scale * sign;
                }
            }
            total
        })
        .collect();
    Ok((T::c(partials.iter().sum::<f64>() / denominator), grad))
}

/// `Σ_t mask[t]·|x[t] − y[t]|` of one row, accumulated in T then returned as f64.
fn row_sum<T: Real>(x: &[T], y: &[T], mask: &[T]) -> f64 {
    let mut acc = [T::zero(); 16];
    let (cx, cy, cm) = (x.chunks_exact(16), y.chunks_exact(16), mask.chunks_exact(16));
    let tail: T = (cx.remainder().iter().zip(cy.remainder()).zip(cm.remainder()))
        .map(|((a, b), m)| *m * (*a - *b).abs())
        .sum();
    for ((a, b), m) in cx.zip(cy).zip(cm) {
        for l in 0..16 {
            acc[l] = m[l].mul_add((a[l] - b[l]).abs(), acc[l]);
        }
    }
    (acc.iter().copied().sum::<T>() + tail)
        .to_f64()
        .unwrap_or(f64::NAN)
}
