//! Masked L1 `Σ_p m_p·Σ_c |x − y| / max(C·Σ_p m_p, 1)` and its subgradient (sign(0) = 0):
//! one pass over the images instead of torch's chain of elementwise kernels. The image may
//! hold more channels than the target (`S ≥ C`, e.g. the mesh's RGBA against an RGB
//! frame): its first `C` are compared where they lie, and its gradient has its layout,
//! zero past them — no copy of the colour, no scatter of its gradient into the RGBA.

use rayon::prelude::*;

use super::forward::expand_mask_row;
use super::{check_weight, SsimInputs, BAND_ROWS};
use crate::error::{check_indices, check_len, Error, Result};
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
        out[t] = slope(mask[t], scale, x[t] - y[t]);
    }
}

/// `out[t] += mask[t]·scale·sign(x[t] − y[t])`: [`slope_row`]'s values added to another
/// term's gradient (the SSIM's), each the same bits as apart.
pub(super) fn add_slope_row<T: Real>(x: &[T], y: &[T], mask: &[T], scale: T, out: &mut [T]) {
    let n = out.len();
    let (x, y, mask) = (&x[..n], &y[..n], &mask[..n]);
    for t in 0..n {
        out[t] += slope(mask[t], scale, x[t] - y[t]);
    }
}

/// One element's L1 subgradient `mask·scale·sign(d)`, the one expression both row passes use.
#[inline(always)]
fn slope<T: Real>(mask: T, scale: T, d: T) -> T {
    mask * scale * sign(d)
}

/// sign(d) with sign(0) = 0 (and NaN → 0), without branches: a residual's sign is a coin
/// toss, and as branches its mispredictions cost more than the rest of a pixel's work.
#[inline(always)]
fn sign<T: Real>(d: T) -> T {
    let (above, below) = (u8::from(d > T::zero()), u8::from(d < T::zero()));
    T::c(f64::from(above)) - T::c(f64::from(below))
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

/// Entries per parallel chunk of [`pixel_l1_with_grad`]; fixed, so the partial sums merge
/// in the same order for any thread count.
const PIXEL_CHUNK: usize = 8192;

/// Borrowed inputs of [`pixel_l1_with_grad`]: values at listed pixels against an image.
#[derive(Debug, Clone, Copy)]
pub struct PixelL1Inputs<'a, T> {
    /// `(P, C)` the values compared (e.g. a mesh's normals at its covered pixels).
    pub values: &'a [T],
    /// `(P,)` each value's flat pixel index `y·W + x` into `target` and `mask`.
    pub pixels: &'a [i64],
    /// `(N, C)` the reference image's pixels (a constant); a pixel of all zeros holds no
    /// data and is not compared.
    pub target: &'a [T],
    /// `(N,)` pixel weights (a constant).
    pub mask: &'a [T],
    /// `C`.
    pub channels: usize,
}

impl<T: Real> PixelL1Inputs<'_, T> {
    /// Shapes and pixel indices; returns `P`.
    fn validate(&self) -> Result<usize> {
        let c = self.channels;
        if c == 0 {
            return Err(Error::Shape {
                arg: "values",
                expected: "(P, C) with C >= 1".into(),
                got: "C = 0".into(),
            });
        }
        let count = self.pixels.len();
        check_len(
            "values",
            self.values,
            count * c,
            &format!("(P, C) = ({count}, {c})"),
        )?;
        let n = self.mask.len();
        check_len(
            "target",
            self.target,
            n * c,
            &format!("(N, C) = ({n}, {c}), N the mask's"),
        )?;
        check_indices("pixels", self.pixels, 0, n as i64)?;
        Ok(count)
    }
}

/// `Σ_p w_p·Σ_c |v_pc − t_{x_p c}| / max(Σ_p w_p, 1)` with `w_p` [`PixelL1Inputs`]'s
/// weight of entry `p` (the mask at its pixel `x_p`, 0 where the target has no data) — the
/// paper's normal loss, mean ‖N − N_gt‖₁ over the covered pixels — and the subgradient of
/// `weight ·` it with respect to the values (sign(0) = 0), the weight folded into the
/// per-entry scale as for [`masked_l1_with_grad`]. Sums in f64, merged in a fixed order:
/// the same bits for any thread count.
pub fn pixel_l1_with_grad<T: Real>(inputs: &PixelL1Inputs<'_, T>, weight: f64) -> Result<(T, Vec<T>)> {
    check_weight(weight)?;
    let count = inputs.validate()?;
    let c = inputs.channels;
    let mut grad = zeroed("pixel L1 gradient (P, C)", count * c)?;
    // One pass over the listed pixels: w·sign(d) per element (exact: the sign is ±1 or 0)
    // and each chunk's Σ w·|d| and Σ w; then the gradient scaled once the total weight is
    // known — the same bits as scaling w by it first.
    let partials: Vec<(f64, f64)> = grad
        .par_chunks_mut(PIXEL_CHUNK * c)
        .enumerate()
        // Three channels (normals) compiled apart: the per-element loops unroll.
        .map(|(k, grad)| match c {
            3 => pixel_l1_chunk(inputs, k, grad, 3),
            _ => pixel_l1_chunk(inputs, k, grad, c),
        })
        .collect();
    let denominator = partials.iter().map(|p| p.1).sum::<f64>().max(1.0);
    let scale = T::c(weight / denominator);
    grad.par_chunks_mut(PIXEL_CHUNK * c).for_each(|chunk| {
        for g in chunk {
            *g *= scale;
        }
    });
    let total: f64 = partials.iter().map(|p| p.0).sum();
    Ok((T::c(total / denominator), grad))
}

/// Chunk `k` of [`pixel_l1_with_grad`]'s pass: writes `w·sign(d)` into `grad` and returns
/// its `(Σ w·|d|, Σ w)`.
#[inline(always)]
fn pixel_l1_chunk<T: Real>(inputs: &PixelL1Inputs<'_, T>, k: usize, grad: &mut [T], c: usize) -> (f64, f64) {
    let (mut total, mut weights) = (0.0, 0.0);
    for (i, g) in grad.chunks_exact_mut(c).enumerate() {
        let p = k * PIXEL_CHUNK + i;
        let pixel = inputs.pixels[p] as usize;
        let v = &inputs.values[p * c..(p + 1) * c];
        let t = &inputs.target[pixel * c..(pixel + 1) * c];
        // the mask at the pixel, 0 where the target holds no data (all zeros)
        let defined = t.iter().fold(false, |any, x| any | (*x != T::zero()));
        let w = if defined { inputs.mask[pixel] } else { T::zero() };
        let mut row = T::zero();
        for ch in 0..c {
            let d = v[ch] - t[ch];
            row += d.abs();
            g[ch] = w * sign(d);
        }
        total += (w * row).to_f64().unwrap_or(f64::NAN);
        weights += w.to_f64().unwrap_or(f64::NAN);
    }
    (total, weights)
}
