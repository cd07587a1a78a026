//! Binning of snapped sub-triangles into screen tiles (full-width bands of `TILE_ROWS`
//! rows). Each tile's list is in sub-triangle order, i.e. by increasing triangle index.

use super::setup::{CoverageRef, Setup};
use super::TILE_ROWS;

pub(crate) struct Bins {
    offsets: Vec<usize>,
    items: Vec<CoverageRef>,
}

impl Bins {
    /// Counting sort by tile; serial, since it is linear in the (small) number of entries.
    pub fn new<T>(setup: &Setup<T>, num_tiles: usize) -> Self {
        let tiles = |y0: u32, y1: u32| y0 as usize / TILE_ROWS..=y1 as usize / TILE_ROWS;
        let mut offsets = vec![0usize; num_tiles + 1];
        for (_, c) in setup.coverage() {
            for t in tiles(c.y0, c.y1) {
                offsets[t + 1] += 1;
            }
        }
        for t in 0..num_tiles {
            offsets[t + 1] += offsets[t];
        }
        let mut fill = offsets.clone();
        let mut items = vec![[0u32; 2]; offsets[num_tiles]];
        for (r, c) in setup.coverage() {
            for t in tiles(c.y0, c.y1) {
                items[fill[t]] = r;
                fill[t] += 1;
            }
        }
        Self { offsets, items }
    }

    /// The sub-triangles overlapping `tile`.
    pub fn tile(&self, tile: usize) -> &[CoverageRef] {
        &self.items[self.offsets[tile]..self.offsets[tile + 1]]
    }
}
