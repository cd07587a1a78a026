//! Masked L1 `Σ_p m_p·Σ_c |x − y| / max(C·Σ_p m_p, 1)` and its subgradient (sign(0) = 0):
//! one pass over the images instead of torch's chain of elementwise kernels. The image may
//! hold more channels than the target (`S ≥ C`, e.g. the mesh's RGBA against an RGB
//! frame): its first `C` are compared where they lie, and its gradient has its layout,
//! zero past them — no copy of the colour, no scatter of its gradient into the RGBA.

use rayon::prelude::*;

use super::forward::expand_mask_row;
use super::{check_weight, SsimInputs, BAND_ROWS};
use crate::error::Result;
use crate::memory::{copy_short, zeroed};
use crate::Real;

/// Masked mean absolute difference.
pub fn masked_l1<T: Real>(inputs: &SsimInputs<'_, T>) -> Result<T> {
    let norm = inputs.validate()?;
    let (len, image_len) = row_lengths(inputs);
    let partials: Vec<f64> = inputs
        .image
        .par_chunks(BAND_ROWS * image_len)
        .zip(inputs.target.par_chunks(BAND_ROWS * len))
        .enumerate()
        .map(|(band, (x, y))| {
            let (mut mask, mut gathered) = (vec![T::zero(); len], gather_buffer(inputs));
            let mut total = 0.0;
            for (i, (x, y)) in x.chunks_exact(image_len).zip(y.chunks_exact(len)).enumerate() {
                expand_mask_row(inputs, band * BAND_ROWS + i, &mut mask);
                total += row_sum(compared(inputs, x, &mut gathered), y, &mask);
            }
            total
        })
        .collect();
    let denominator = (norm * inputs.channels as f64).max(1.0);
    Ok(T::c(partials.iter().sum::<f64>() / denominator))
}

/// Masked mean absolute difference and the subgradient of `weight ·` it with respect to
/// `image` (the weight folded into the per-pixel scale, as for SSIM).
pub fn masked_l1_with_grad<T: Real>(inputs: &SsimInputs<'_, T>, weight: f64) -> Result<(T, Vec<T>)> {
    check_weight(weight)?;
    let norm = inputs.validate()?;
    let (len, image_len) = row_lengths(inputs);
    let (c, s) = (inputs.channels, inputs.image_channels);
    let denominator = (norm * c as f64).max(1.0);
    let scale = T::c(weight / denominator);
    let mut grad = zeroed("L1 gradient (H, W, S)", inputs.height * image_len)?;
    let partials: Vec<f64> = grad
        .par_chunks_mut(BAND_ROWS * image_len)
        .zip(inputs.image.par_chunks(BAND_ROWS * image_len))
        .zip(inputs.target.par_chunks(BAND_ROWS * len))
        .enumerate()
        .map(|(band, ((grad, x), y))| {
            let (mut mask, mut gathered) = (vec![T::zero(); len], gather_buffer(inputs));
            let mut slopes = gather_buffer(inputs);
            let mut total = 0.0;
            let image_rows = grad.chunks_exact_mut(image_len).zip(x.chunks_exact(image_len));
            for (i, ((g, x), y)) in image_rows.zip(y.chunks_exact(len)).enumerate() {
                expand_mask_row(inputs, band * BAND_ROWS + i, &mut mask);
                let x = compared(inputs, x, &mut gathered);
                total += row_sum(x, y, &mask);
                if s == c {
                    slope_row(x, y, &mask, scale, g);
                } else {
                    slope_row(x, y, &mask, scale, &mut slopes);
                    copy_pixels(g, s, &slopes, c, c);
                }
            }
            total
        })
        .collect();
    Ok((T::c(partials.iter().sum::<f64>() / denominator), grad))
}

/// `out[t] = mask[t]·scale·sign(x[t] − y[t])` (sign(0) = 0) over one row.
fn slope_row<T: Real>(x: &[T], y: &[T], mask: &[T], scale: T, out: &mut [T]) {
    let n = out.len();
    let (x, y, mask) = (&x[..n], &y[..n], &mask[..n]);
    for t in 0..n {
        out[t] = mask[t] * scale * sign(x[t] - y[t]);
    }
}

/// `out[t] += mask[t]·scale·sign(x[t] − y[t])`: [`slope_row`]'s values added to another
/// term's gradient (the SSIM's), each the same bits as apart.
pub(super) fn add_slope_row<T: Real>(x: &[T], y: &[T], mask: &[T], scale: T, out: &mut [T]) {
    let n = out.len();
    let (x, y, mask) = (&x[..n], &y[..n], &mask[..n]);
    for t in 0..n {
        out[t] += mask[t] * scale * sign(x[t] - y[t]);
    }
}

/// sign(d) with sign(0) = 0 (and NaN → 0).
#[inline(always)]
fn sign<T: Real>(d: T) -> T {
    if d > T::zero() {
        T::one()
    } else if d < T::zero() {
        -T::one()
    } else {
        T::zero()
    }
}

/// A row's length in the target (`W·C`) and in the image (`W·S`).
fn row_lengths<T>(inputs: &SsimInputs<'_, T>) -> (usize, usize) {
    (
        inputs.width * inputs.channels,
        inputs.width * inputs.image_channels,
    )
}

/// A row buffer in the target's layout (`W·C`) for an image wider than the target; empty
/// when they match (nothing is gathered then).
fn gather_buffer<T: Real>(inputs: &SsimInputs<'_, T>) -> Vec<T> {
    let wider = inputs.image_channels != inputs.channels;
    vec![T::zero(); if wider { inputs.width * inputs.channels } else { 0 }]
}

/// Image row `x` (`W·S`) in the target's layout (`W·C`): itself when `S = C`, else its
/// compared channels gathered into `gathered`.
fn compared<'a, T: Real>(inputs: &SsimInputs<'_, T>, x: &'a [T], gathered: &'a mut [T]) -> &'a [T] {
    let (c, s) = (inputs.channels, inputs.image_channels);
    if s == c {
        return x;
    }
    copy_pixels(gathered, c, x, s, c);
    gathered
}

/// The first `n` channels of each pixel of `src` (pixels `src_stride` apart) into the
/// pixels of `dst` (`dst_stride` apart). Three channels, the colour of an RGB or RGBA
/// image, are copied as a fixed-size move: a copy of a length known only at run time is
/// a `memmove` call per pixel, which took ~15 % of the masked L1 on an RGBA image.
fn copy_pixels<T: Copy>(dst: &mut [T], dst_stride: usize, src: &[T], src_stride: usize, n: usize) {
    let pixels = dst.chunks_exact_mut(dst_stride).zip(src.chunks_exact(src_stride));
    if n == 3 {
        for (d, s) in pixels {
            d[..3].copy_from_slice(&s[..3]);
        }
    } else {
        for (d, s) in pixels {
            copy_short(d, s, n);
        }
    }
}

/// `Σ_t mask[t]·|x[t] − y[t]|` of one row, accumulated in T then returned as f64.
pub(super) fn row_sum<T: Real>(x: &[T], y: &[T], mask: &[T]) -> f64 {
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
