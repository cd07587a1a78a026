//! The separable Gaussian blur as streaming row operations on interleaved `(H, W, C)` maps.
//!
//! A horizontal pass reads a zero-padded row whose taps are `C` elements apart; a vertical
//! pass sums the 11 horizontally blurred rows around the output row, kept in a ring. Rows
//! outside the image read as zeros, which is conv2d's zero padding.

use std::ops::Range;

use super::WINDOW;
use crate::Real;

const HALF: usize = WINDOW / 2;

/// Elements accumulated together: 4 AVX2 registers of f32 (8 of f64), enough independent
/// FMA chains to hide their latency.
const LANES: usize = 32;

/// `out[t] = Σ_k weights[k]·sources[k][t]` for a symmetric window (`weights[k] ==
/// weights[10 − k]`), each `sources[k]` at least `out.len()` long. Pairing mirrored taps
/// turns 11 multiply-adds into 5 adds and 6 multiply-adds, which run on separate ports.
#[inline]
pub(super) fn symmetric_weighted_sum<T: Real>(
    out: &mut [T],
    sources: &[&[T]; WINDOW],
    weights: &[T; WINDOW],
) {
    let n = out.len();
    assert!(
        sources.iter().all(|s| s.len() >= n),
        "blur source rows are too short"
    );
    debug_assert!((0..HALF).all(|k| weights[k] == weights[WINDOW - 1 - k]));
    let full = n - n % LANES;
    for (block, start) in out[..full].chunks_exact_mut(LANES).zip((0..full).step_by(LANES)) {
        let centre = &sources[HALF][start..start + LANES];
        let mut acc: [T; LANES] = std::array::from_fn(|l| weights[HALF] * centre[l]);
        for k in 0..HALF {
            let low = &sources[k][start..start + LANES];
            let high = &sources[WINDOW - 1 - k][start..start + LANES];
            for l in 0..LANES {
                acc[l] = weights[k].mul_add(low[l] + high[l], acc[l]);
            }
        }
        block.copy_from_slice(&acc);
    }
    for t in full..n {
        let mut acc = weights[HALF] * sources[HALF][t];
        for k in 0..HALF {
            acc = weights[k].mul_add(sources[k][t] + sources[WINDOW - 1 - k][t], acc);
        }
        out[t] = acc;
    }
}

/// `N` interleaved rows of `W·C` values, each with `5·C` zeros on either side, so the
/// horizontal pass needs no bounds logic.
pub(super) struct PaddedRows<T, const N: usize> {
    channels: usize,
    row_len: usize,
    data: Vec<T>,
}

impl<T: Real, const N: usize> PaddedRows<T, N> {
    pub(super) fn new(width: usize, channels: usize) -> Self {
        let row_len = width * channels;
        Self {
            channels,
            row_len,
            data: vec![T::zero(); N * (row_len + 2 * HALF * channels)],
        }
    }

    /// The `N` interior rows (`W·C` each), to be filled before `blur_into`.
    pub(super) fn interiors_mut(&mut self) -> [&mut [T]; N] {
        let (margin, len) = (HALF * self.channels, self.row_len);
        let mut rows = self.data.chunks_exact_mut(len + 2 * margin);
        std::array::from_fn(|_| &mut rows.next().expect("N padded rows")[margin..margin + len])
    }

    /// Horizontal blur of the `N` rows into `out`, `N` consecutive rows of `W·C`, at the
    /// elements `range` of each row only (the rest of `out` is left as it was). Reads the
    /// interiors `HALF·C` elements either side of `range`.
    pub(super) fn blur_into(&self, weights: &[T; WINDOW], range: &Range<usize>, out: &mut [T]) {
        let (c, len) = (self.channels, self.row_len);
        for (padded, dst) in self
            .data
            .chunks_exact(len + 2 * HALF * c)
            .zip(out.chunks_exact_mut(len))
        {
            let taps: [&[T]; WINDOW] =
                std::array::from_fn(|k| &padded[k * c + range.start..k * c + range.end]);
            symmetric_weighted_sum(&mut dst[range.clone()], &taps, weights);
        }
    }
}

/// The last `WINDOW` horizontally blurred image rows (each `N·W·C`, the `N` maps of one
/// image row side by side), addressed by image row.
pub(super) struct RowRing<T> {
    height: usize,
    row_len: usize,
    slot_len: usize,
    slots: Vec<T>,
    zeros: Vec<T>,
}

impl<T: Real> RowRing<T> {
    /// A ring of `maps` maps of rows of `row_len` elements.
    pub(super) fn new(height: usize, maps: usize, row_len: usize) -> Self {
        let slot_len = maps * row_len;
        Self {
            height,
            row_len,
            slot_len,
            slots: vec![T::zero(); WINDOW * slot_len],
            zeros: vec![T::zero(); slot_len],
        }
    }

    /// Storage for image row `row`, replacing row `row − WINDOW`.
    pub(super) fn slot_mut(&mut self, row: usize) -> &mut [T] {
        let start = (row % WINDOW) * self.slot_len;
        &mut self.slots[start..start + self.slot_len]
    }

    /// Vertical blur centred on image row `row` into `out` (`slot_len`), at the elements
    /// `range` of each map's row only (the rest of `out` is left as it was). The in-image
    /// rows `row − 5 ..= row + 5` must be the last ones stored, valid on `range`.
    pub(super) fn blur_column(&self, row: usize, weights: &[T; WINDOW], range: &Range<usize>, out: &mut [T]) {
        let sources: [&[T]; WINDOW] = std::array::from_fn(|k| match (row + k).checked_sub(HALF) {
            Some(r) if r < self.height => {
                let start = (r % WINDOW) * self.slot_len;
                &self.slots[start..start + self.slot_len]
            }
            _ => &self.zeros[..],
        });
        for (map, dst) in out.chunks_exact_mut(self.row_len).enumerate() {
            let (start, end) = (map * self.row_len + range.start, map * self.row_len + range.end);
            let taps: [&[T]; WINDOW] = std::array::from_fn(|k| &sources[k][start..end]);
            symmetric_weighted_sum(&mut dst[range.clone()], &taps, weights);
        }
    }
}
