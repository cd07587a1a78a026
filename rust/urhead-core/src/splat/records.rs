//! Per-chunk compositing records of the backward's front-to-back replay: for every 8-pixel
//! chunk a Gaussian contributed to, the transmittance before the sample, g = exp(−σ), the
//! chunk's slot in its tile and the contributing lanes.
//!
//! (Keeping these from the forward instead of replaying was measured: about 60 MB per
//! call for 30k Gaussians at 512², and the page faults of that fresh memory cost more
//! than the replay saves.)

use super::lanes::{Lanes, WIDTH};
use super::raster::{Splat, TileState};
use crate::Real;

/// Records of one replayed segment of a tile list.
#[derive(Debug, Clone, Default)]
pub struct RowRecords<T> {
    /// `(R, 8)` T before the sample.
    t: Vec<T>,
    /// `(R, 8)` exp(−σ).
    g: Vec<T>,
    /// `(R,)` (slot in the tile, contributing-lane bits).
    meta: Vec<(u8, u8)>,
    /// One entry per visited Gaussian in list order: the end of its records.
    ends: Vec<u32>,
}

impl<T: Real> RowRecords<T> {
    pub(super) fn clear(&mut self) {
        self.t.clear();
        self.g.clear();
        self.meta.clear();
        self.ends.clear();
    }

    #[inline(always)]
    pub(super) fn push<L: Lanes<Elem = T>>(&mut self, t: L, g: L, slot: usize, bits: u8) {
        self.t.extend_from_slice(&t.to_array());
        self.g.extend_from_slice(&g.to_array());
        self.meta.push((slot as u8, bits));
    }

    /// Records `[r0, r1)` of the Gaussian at `ends[index]`.
    #[inline(always)]
    pub(super) fn range(&self, index: usize) -> std::ops::Range<usize> {
        let r0 = if index == 0 {
            0
        } else {
            self.ends[index - 1] as usize
        };
        r0..self.ends[index] as usize
    }

    /// Record `r`: (T before, g, slot, contributing bits).
    #[inline(always)]
    pub(super) fn get<L: Lanes<Elem = T>>(&self, r: usize) -> (L, L, usize, u8) {
        let lanes = |v: &[T]| {
            let chunk: [T; WIDTH] = v[r * WIDTH..(r + 1) * WIDTH]
                .try_into()
                .expect("records hold 8 lanes");
            L::from_array(chunk)
        };
        let (slot, bits) = self.meta[r];
        (lanes(&self.t), lanes(&self.g), slot as usize, bits)
    }
}

/// Visits one Gaussian, recording every chunk it contributes to.
#[inline(always)]
pub(super) fn record_gaussian<L: Lanes>(
    st: &mut TileState<L>,
    s: &Splat<L::Elem>,
    recs: &mut RowRecords<L::Elem>,
) {
    st.visit_gaussian(s, |slot, _alpha, g, t, contrib| {
        let bits = L::mask_bits(contrib);
        if bits != 0 {
            recs.push(t, g, slot, bits);
        }
    });
    recs.ends.push(recs.meta.len() as u32);
}
