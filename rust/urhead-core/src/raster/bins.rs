//! Binning of snapped sub-triangles into screen tiles (full-width bands of `TILE_ROWS`
//! rows). Each tile's list is in sub-triangle order, i.e. by increasing triangle index.

use super::setup::CoverageTri;
use super::TILE_ROWS;

pub(crate) struct Bins {
    offsets: Vec<usize>,
    items: Vec<u32>,
}

impl Bins {
    /// Counting sort by tile; serial, since it is linear in the (small) number of entries.
    pub fn new(coverage: &[CoverageTri], num_tiles: usize) -> Self {
        let tiles = |c: &CoverageTri| c.y0 / TILE_ROWS..=c.y1 / TILE_ROWS;
        let mut offsets = vec![0usize; num_tiles + 1];
        for c in coverage {
            for t in tiles(c) {
                offsets[t + 1] += 1;
            }
        }
        for t in 0..num_tiles {
            offsets[t + 1] += offsets[t];
        }
        let mut fill = offsets.clone();
        let mut items = vec![0u32; offsets[num_tiles]];
        for (i, c) in coverage.iter().enumerate() {
            for t in tiles(c) {
                items[fill[t]] = i as u32;
                fill[t] += 1;
            }
        }
        Self { offsets, items }
    }

    /// Indices into the coverage list of the sub-triangles overlapping `tile`.
    pub fn tile(&self, tile: usize) -> &[u32] {
        &self.items[self.offsets[tile]..self.offsets[tile + 1]]
    }
}
