//! Forward: the five blurred moments (μx, μy, E[x²], E[y²], E[xy]) streamed row by row, the
//! per-pixel SSIM, and its masked mean.

use std::ops::Range;

use rayon::prelude::*;

use super::blur::{PaddedRows, RowRing};
use super::{bands, elements, gaussian_window, widened, PixelTerms, SsimInputs, WINDOW};
use crate::error::Result;
use crate::parallel::dot;
use crate::Real;

/// Moments of one image row, map by map: μx, μy, E[x²], E[y²], E[xy], each `W·C`.
pub(super) const MOMENTS: usize = 5;

/// Streams the blurred moments of increasing image rows on a window of pixel columns,
/// computing each input row's horizontal pass once.
pub(super) struct MomentStream<'a, T> {
    inputs: &'a SsimInputs<'a, T>,
    weights: [T; WINDOW],
    products: PaddedRows<T, MOMENTS>,
    ring: RowRing<T>,
    moments: Vec<T>,
    /// The elements of a row where moments are wanted, and those widened by the window:
    /// what their horizontal pass reads (and how far a blur of values on them reaches).
    wanted: Range<usize>,
    reach: Range<usize>,
    /// The next input row to blur horizontally.
    next_input: usize,
}

impl<'a, T: Real> MomentStream<'a, T> {
    /// A stream whose first requested row is `first_row`, with moments at the pixel
    /// columns `columns`.
    pub(super) fn new(inputs: &'a SsimInputs<'a, T>, first_row: usize, columns: &Range<usize>) -> Self {
        let (c, row_len) = (inputs.channels, inputs.width * inputs.channels);
        Self {
            inputs,
            weights: gaussian_window(),
            products: PaddedRows::new(inputs.width, c),
            ring: RowRing::new(inputs.height, MOMENTS, row_len),
            moments: vec![T::zero(); MOMENTS * row_len],
            wanted: elements(columns, c),
            reach: elements(&widened(columns, inputs.width), c),
            next_input: first_row.saturating_sub(WINDOW / 2),
        }
    }

    /// The elements of a row where the stream's moments are valid (its columns).
    pub(super) fn wanted(&self) -> Range<usize> {
        self.wanted.clone()
    }

    /// The elements a blur of values on the stream's columns can reach (its columns
    /// widened by the window).
    pub(super) fn reach(&self) -> Range<usize> {
        self.reach.clone()
    }

    /// The moments of image row `row` (`MOMENTS` maps of `W·C`, valid on the stream's
    /// columns); rows must be requested in increasing order.
    pub(super) fn row(&mut self, row: usize) -> &[T] {
        let last_needed = (row + WINDOW / 2).min(self.inputs.height - 1);
        while self.next_input <= last_needed {
            self.push_input(self.next_input);
            self.next_input += 1;
        }
        self.ring
            .blur_column(row, &self.weights, &self.wanted, &mut self.moments);
        &self.moments
    }

    fn push_input(&mut self, row: usize) {
        let len = self.inputs.width * self.inputs.channels;
        let x = &self.inputs.image[row * len..(row + 1) * len];
        let y = &self.inputs.target[row * len..(row + 1) * len];
        let [px, py, pxx, pyy, pxy] = self.products.interiors_mut();
        for t in self.reach.clone() {
            let (a, b) = (x[t], y[t]);
            px[t] = a;
            py[t] = b;
            pxx[t] = a * a;
            pyy[t] = b * b;
            pxy[t] = a * b;
        }
        self.products
            .blur_into(&self.weights, &self.wanted, self.ring.slot_mut(row));
    }
}

/// The mask weight of each element of image row `row` (`W·C`, repeated over channels).
pub(super) fn expand_mask_row<T: Real>(inputs: &SsimInputs<'_, T>, row: usize, out: &mut [T]) {
    let (w, c) = (inputs.width, inputs.channels);
    for (j, pixel) in out.chunks_exact_mut(c).enumerate() {
        pixel.fill(inputs.mask_weight(row * w + j));
    }
}

/// Per-element SSIM of one row from its moments, into `out` (`W·C`) at the elements
/// `range` (the rest of `out` is left as it was).
pub(super) fn ssim_row<T: Real>(moments: &[T], range: &Range<usize>, out: &mut [T]) {
    let len = out.len();
    let [mu_x, mu_y, e_xx, e_yy, e_xy]: [&[T]; MOMENTS] =
        std::array::from_fn(|m| &moments[m * len..(m + 1) * len]);
    for t in range.clone() {
        out[t] = PixelTerms::new(mu_x[t], mu_y[t], e_xx[t], e_yy[t], e_xy[t]).ssim();
    }
}

/// Masked mean SSIM `Σ_p m_p·ssim_p / max(Σ_p m_p, 1)`, ssim_p averaged over channels.
pub fn masked_ssim<T: Real>(inputs: &SsimInputs<'_, T>) -> Result<T> {
    let norm = inputs.validate_same_channels()?.max(1.0);
    let len = inputs.width * inputs.channels;
    let partials: Vec<f64> = bands(inputs.height)
        .map(|(start, end)| {
            let columns = inputs.ssim_columns(start..end);
            let mut stream = MomentStream::new(inputs, start, &columns);
            let wanted = stream.wanted();
            // SSIM is exactly 1 off `columns` (see `ssim_columns`).
            let (mut ssim, mut weights) = (vec![T::one(); len], vec![T::zero(); len]);
            let mut total = 0.0;
            for row in start..end {
                ssim_row(stream.row(row), &wanted, &mut ssim);
                expand_mask_row(inputs, row, &mut weights);
                total += dot(&ssim, &weights).to_f64().unwrap_or(f64::NAN);
            }
            total
        })
        .collect();
    let total: f64 = partials.iter().sum();
    Ok(T::c(total / (norm * inputs.channels as f64)))
}
