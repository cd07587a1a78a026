//! Masked mean SSIM of `(H, W, C)` images and its gradient, fused for the training loop.
//!
//! SSIM as 3DGS and `urhead.losses.ssim_map` define it: an 11 × 11 Gaussian window
//! (σ = 1.5) applied separably with zero padding, C1 = 0.01², C2 = 0.03², the per-pixel
//! value averaged over channels. The loss is the masked mean `Σ_p m_p·ssim_p / max(Σ_p m_p, 1)`.
//! The masked L1 `Σ m·|x − y| / max(C·Σ m, 1)` of the same loss stage lives here too.
//!
//! Layout: images stay interleaved. A horizontal blur of an interleaved row is a 1-D blur
//! whose taps are `C` elements apart, and a vertical blur sums 11 whole rows, so both
//! passes are contiguous multiply-adds over `W·C` elements (AVX2-friendly) and no channel
//! is ever de-interleaved.
//!
//! Work is cut into fixed bands of rows; each band streams its rows through ring buffers
//! of 11 horizontally blurred rows (L2-resident), recomputing the few halo rows it shares
//! with its neighbours instead of materialising full-image intermediates. Pixels do not
//! depend on the banding; per-band sums are merged in band order, so results are bitwise
//! identical for any thread count. A band computes only on the columns where its rows'
//! mask is positive and the image differs from the target within a window
//! (`SsimInputs::ssim_columns`): a head fills about a third of its frame, and a render's
//! background equals the photo's.

mod backward;
mod blur;
mod forward;
mod l1;

pub use backward::{masked_ssim_l1_with_grad, masked_ssim_with_grad};
pub use forward::masked_ssim;
pub use l1::{masked_l1, masked_l1_with_grad, pixel_l1_with_grad, PixelL1Inputs};

use std::ops::Range;

use rayon::prelude::*;

use crate::error::{check_finite, check_len, first_where, Error, Result};
use crate::Real;

/// Side of the Gaussian window.
pub const WINDOW: usize = 11;
/// Standard deviation of the Gaussian window, in pixels.
pub const SIGMA: f64 = 1.5;
/// Stabiliser of the luminance term, (0.01·L)² for L = 1.
pub const C1: f64 = 0.01 * 0.01;
/// Stabiliser of the contrast-structure term, (0.03·L)².
pub const C2: f64 = 0.03 * 0.03;

/// Image rows per parallel work item. Fixed (never derived from the thread count) so the
/// order of the per-band partial sums, and hence the result bits, never change.
const BAND_ROWS: usize = 128;

/// Elements per parallel chunk of the mask sum.
const CHECK_CHUNK: usize = 1 << 16;

/// Borrowed inputs of one SSIM evaluation.
#[derive(Debug, Clone, Copy)]
pub struct SsimInputs<'a, T> {
    /// `(H, W, S)` image the gradient is taken with respect to; its first `C` channels are
    /// compared (an RGBA image read in place against an RGB target, for L1; SSIM needs
    /// `S = C`).
    pub image: &'a [T],
    /// `(H, W, C)` reference image (a constant).
    pub target: &'a [T],
    /// `(H, W)` pixel weights in [0, 1], or `None` for all ones.
    pub mask: Option<&'a [T]>,
    pub height: usize,
    pub width: usize,
    /// `C`, the target's channels.
    pub channels: usize,
    /// `S ≥ C`, the image's channels.
    pub image_channels: usize,
}

impl<T: Real> SsimInputs<'_, T> {
    /// Shapes, finiteness and mask range; returns the mask weight `Σ m` (`H·W` without one).
    fn validate(&self) -> Result<f64> {
        let (h, w, c, s) = (self.height, self.width, self.channels, self.image_channels);
        if h == 0 || w == 0 || c == 0 || s < c {
            return Err(Error::Shape {
                arg: "image",
                expected: "(H, W, S) with H, W >= 1 and S >= C >= 1 (C the target's channels)".into(),
                got: format!("({h}, {w}, {s}) with C = {c}"),
            });
        }
        check_len(
            "image",
            self.image,
            h * w * s,
            &format!("(H, W, S) = ({h}, {w}, {s})"),
        )?;
        check_len(
            "target",
            self.target,
            h * w * c,
            &format!("(H, W, C) = ({h}, {w}, {c})"),
        )?;
        check_finite("image", self.image)?;
        check_finite("target", self.target)?;
        let Some(mask) = self.mask else {
            return Ok((h * w) as f64);
        };
        check_len("mask", mask, h * w, &format!("(H, W) = ({h}, {w})"))?;
        check_finite("mask", mask)?;
        if let Some(i) = first_where(mask, |&m| (m < T::zero()) | (m > T::one())) {
            return Err(Error::Invalid {
                arg: "mask",
                reason: format!("weights must be in [0, 1], got {:?} at flat index {i}", mask[i]),
            });
        }
        let partials: Vec<f64> = mask
            .par_chunks(CHECK_CHUNK)
            .map(|chunk| chunk.iter().map(|m| m.to_f64().unwrap_or(0.0)).sum())
            .collect();
        Ok(partials.iter().sum())
    }

    /// [`Self::validate`] for SSIM, which compares whole images (`S = C`).
    fn validate_same_channels(&self) -> Result<f64> {
        if self.image_channels != self.channels {
            return Err(Error::Shape {
                arg: "image",
                expected: format!("the target's {} channels for SSIM", self.channels),
                got: format!("{} channels", self.image_channels),
            });
        }
        self.validate()
    }

    /// The pixel columns `[a, b)` of rows `rows` on which SSIM is computed (empty for none):
    /// those holding every pixel of a positive mask weight (all without a mask) whose window
    /// reaches a pixel where the image and the target differ. Elsewhere the pixel adds
    /// `0·ssim` to the mean, or its window shows the image equal to the target, where SSIM
    /// is at its maximum: exactly 1, with an exactly zero gradient. A head fills about a
    /// third of its frame, and a render's background is the target's exactly.
    fn ssim_columns(&self, rows: Range<usize>) -> Range<usize> {
        let weighted = self.weighted_columns(rows.clone());
        if weighted.is_empty() {
            return weighted;
        }
        let half = WINDOW / 2;
        let window_rows = rows.start.saturating_sub(half)..(rows.end + half).min(self.height);
        let reached = widened(&self.differing_columns(window_rows), self.width);
        span(weighted.start.max(reached.start), weighted.end.min(reached.end))
    }

    /// The pixel columns `[a, b)` holding every pixel of `rows` with a positive mask weight
    /// (every column without a mask; empty when there is none).
    fn weighted_columns(&self, rows: Range<usize>) -> Range<usize> {
        let w = self.width;
        let Some(mask) = self.mask else {
            return 0..w;
        };
        columns_where(&mask[rows.start * w..rows.end * w], None, w, 1)
    }

    /// The pixel columns `[a, b)` holding every pixel of `rows` where the image and the
    /// target differ in some channel (empty when they are equal).
    fn differing_columns(&self, rows: Range<usize>) -> Range<usize> {
        let len = self.width * self.channels;
        let span = rows.start * len..rows.end * len;
        columns_where(
            &self.image[span.clone()],
            Some(&self.target[span]),
            len,
            self.channels,
        )
    }

    /// Weight of pixel `p` in the masked mean, before normalisation.
    #[inline(always)]
    fn mask_weight(&self, pixel: usize) -> T {
        self.mask.map_or(T::one(), |m| m[pixel])
    }
}

/// A loss term's weight, which scales every gradient entry: finite.
fn check_weight(weight: f64) -> Result<()> {
    if weight.is_finite() {
        return Ok(());
    }
    Err(Error::Invalid {
        arg: "weight",
        reason: format!("must be finite, got {weight}"),
    })
}

/// The normalised 11-tap Gaussian, computed in f64 then rounded once.
fn gaussian_window<T: Real>() -> [T; WINDOW] {
    let half = (WINDOW / 2) as f64;
    let raw: Vec<f64> = (0..WINDOW)
        .map(|i| (-((i as f64 - half).powi(2)) / (2.0 * SIGMA * SIGMA)).exp())
        .collect();
    let total: f64 = raw.iter().sum();
    std::array::from_fn(|i| T::c(raw[i] / total))
}

/// The blurred moments of one pixel and channel, and the SSIM terms built from them.
#[derive(Debug, Clone, Copy)]
struct PixelTerms<T> {
    mu_x: T,
    mu_y: T,
    /// 2·μx·μy + C1
    a1: T,
    /// 2·σxy + C2
    a2: T,
    /// μx² + μy² + C1
    b1: T,
    /// σx² + σy² + C2
    b2: T,
}

impl<T: Real> PixelTerms<T> {
    /// From the blurred x, y, x², y², x·y.
    #[inline(always)]
    fn new(mu_x: T, mu_y: T, e_xx: T, e_yy: T, e_xy: T) -> Self {
        let (c1, c2, two) = (T::c(C1), T::c(C2), T::c(2.0));
        let (mx2, my2, mxy) = (mu_x * mu_x, mu_y * mu_y, mu_x * mu_y);
        Self {
            mu_x,
            mu_y,
            a1: two * mxy + c1,
            a2: two * (e_xy - mxy) + c2,
            b1: mx2 + my2 + c1,
            b2: (e_xx - mx2) + (e_yy - my2) + c2,
        }
    }

    /// `(1/B1, 1/B2)` from one division, shared by the value and the adjoint so both give
    /// the same SSIM bits.
    #[inline(always)]
    fn inverses(&self) -> (T, T) {
        let inv = T::one() / (self.b1 * self.b2);
        (self.b2 * inv, self.b1 * inv)
    }

    #[inline(always)]
    fn ssim(&self) -> T {
        let (inv_b1, inv_b2) = self.inverses();
        self.a1 * self.a2 * (inv_b1 * inv_b2)
    }
}

/// The columns `[a, b)` (of `channels` elements each) holding every element of the rows
/// of `row_len` elements of `values` that is positive, or, given `others`, that differs
/// from its counterpart there (empty for none). Each row is scanned from either end only
/// up to the columns already found.
fn columns_where<T: Real>(
    values: &[T],
    others: Option<&[T]>,
    row_len: usize,
    channels: usize,
) -> Range<usize> {
    let columns = row_len / channels;
    let (mut a, mut b) = (columns, 0);
    for start in (0..values.len()).step_by(row_len) {
        let part = |range: Range<usize>| {
            let range = start + range.start..start + range.end;
            (&values[range.clone()], others.map(|o| &o[range]))
        };
        let (left, left_others) = part(0..a * channels);
        if let Some(t) = find_hit::<T, false>(left, left_others) {
            a = t / channels;
        }
        let (right, right_others) = part(b * channels..row_len);
        if let Some(t) = find_hit::<T, true>(right, right_others) {
            b += t / channels + 1;
        }
    }
    span(a, b)
}

/// The columns `[a, b)`, or `0..0` when there are none.
fn span(a: usize, b: usize) -> Range<usize> {
    if a < b {
        a..b
    } else {
        0..0
    }
}

/// Elements tested together by [`find_hit`], without an early exit
/// (so the test vectorises).
const HIT_BLOCK: usize = 32;

/// Whether `values[i]` is positive, or, given `others`, differs from `others[i]`.
#[inline(always)]
fn hit<T: Real>(values: &[T], others: Option<&[T]>, i: usize) -> bool {
    match others {
        None => values[i] > T::zero(),
        Some(others) => values[i] != others[i],
    }
}

/// Whether some element of the block hits (see [`hit`]).
#[inline(always)]
fn block_hits<T: Real>(values: &[T], others: Option<&[T]>) -> bool {
    match others {
        None => values.iter().fold(false, |any, v| any | (*v > T::zero())),
        Some(others) => values
            .iter()
            .zip(others)
            .fold(false, |any, (x, y)| any | (x != y)),
    }
}

/// The first index whose element hits (see [`hit`]), or with `FROM_END` the last: blocks
/// are tested whole, and only the block that hits is searched element by element.
fn find_hit<T: Real, const FROM_END: bool>(values: &[T], others: Option<&[T]>) -> Option<usize> {
    let in_block = |start: usize| {
        let block = start..(start + HIT_BLOCK).min(values.len());
        if !block_hits(&values[block.clone()], others.map(|o| &o[block.clone()])) {
            return None;
        }
        let is_hit = |i: &usize| hit(values, others, *i);
        if FROM_END {
            block.rev().find(is_hit)
        } else {
            block.clone().find(is_hit)
        }
    };
    let blocks = (0..values.len()).step_by(HIT_BLOCK);
    if FROM_END {
        blocks.rev().find_map(in_block)
    } else {
        blocks.into_iter().find_map(in_block)
    }
}

/// Pixel columns `columns` widened by the window's half width on either side, within
/// `[0, width)` (still empty when empty): where a blur of values living on `columns` can
/// be non-zero, and what a blur onto `columns` reads.
fn widened(columns: &Range<usize>, width: usize) -> Range<usize> {
    if columns.is_empty() {
        return columns.clone();
    }
    columns.start.saturating_sub(WINDOW / 2)..(columns.end + WINDOW / 2).min(width)
}

/// The interleaved elements `(…, C)` of pixel columns `columns`.
fn elements(columns: &Range<usize>, channels: usize) -> Range<usize> {
    columns.start * channels..columns.end * channels
}

/// The band boundaries `[start, end)` of an image of `height` rows.
fn bands(height: usize) -> impl IndexedParallelIterator<Item = (usize, usize)> {
    (0..height.div_ceil(BAND_ROWS))
        .into_par_iter()
        .map(move |b| (b * BAND_ROWS, ((b + 1) * BAND_ROWS).min(height)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;

    /// The definition: every column with a hit in some row, as a hull.
    fn hull(values: &[f32], others: Option<&[f32]>, row_len: usize, channels: usize) -> Range<usize> {
        let cols: Vec<usize> = (0..values.len())
            .filter(|&i| hit(values, others, i))
            .map(|i| i % row_len / channels)
            .collect();
        match (cols.iter().min(), cols.iter().max()) {
            (Some(&a), Some(&b)) => a..b + 1,
            _ => 0..0,
        }
    }

    #[test]
    fn columns_where_is_the_hull_of_the_hits() {
        let mut rng = Rng::new(7);
        for (rows, columns, channels) in [(1, 1, 1), (3, 5, 3), (4, 70, 1), (6, 41, 3), (2, 200, 2)] {
            let len = rows * columns * channels;
            for density in [0.0, 0.002, 0.02, 0.3] {
                let sparse = |rng: &mut Rng| -> Vec<f32> {
                    (0..len)
                        .map(|_| if rng.uniform(0.0, 1.0) < density { 0.5 } else { 0.0 })
                        .collect()
                };
                let (values, others) = (sparse(&mut rng), vec![0.0; len]);
                let row_len = columns * channels;
                assert_eq!(
                    columns_where(&values, None, row_len, channels),
                    hull(&values, None, row_len, channels),
                    "positive, {rows}×{columns}×{channels} at {density}"
                );
                assert_eq!(
                    columns_where(&values, Some(&others), row_len, channels),
                    hull(&values, Some(&others), row_len, channels),
                    "differing, {rows}×{columns}×{channels} at {density}"
                );
            }
        }
    }
}
