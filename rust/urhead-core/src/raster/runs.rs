//! Deterministic scatter of per-pixel gradient contributions to triangles: each screen tile
//! accumulates runs of consecutive pixels that hit the same triangle (no float atomics),
//! and the runs are merged into a per-triangle table in tile order, then pixel order.

use crate::Real;

/// Per-tile list of `(triangle, width sums)` runs, in pixel order.
pub(crate) struct TriangleRuns<T> {
    width: usize,
    tris: Vec<u32>,
    sums: Vec<T>,
}

impl<T: Real> TriangleRuns<T> {
    pub fn new(width: usize) -> Self {
        Self {
            width,
            tris: Vec::new(),
            sums: Vec::new(),
        }
    }

    /// The accumulator of `tri`: the current run's if it is the same triangle, else a new
    /// zeroed one.
    #[inline(always)]
    pub fn slot(&mut self, tri: u32) -> &mut [T] {
        if self.tris.last() != Some(&tri) {
            return self.new_slot(tri);
        }
        let n = self.sums.len();
        &mut self.sums[n - self.width..]
    }

    /// A new zeroed accumulator of `tri`, ending the current run even if it is the same
    /// triangle.
    #[inline(always)]
    pub fn new_slot(&mut self, tri: u32) -> &mut [T] {
        self.tris.push(tri);
        self.sums.resize(self.sums.len() + self.width, T::zero());
        let n = self.sums.len();
        &mut self.sums[n - self.width..]
    }
}

/// Sums all runs into a dense `(num_tris, width)` table, in the order given.
pub(crate) fn merge_runs<T: Real>(runs: &[TriangleRuns<T>], num_tris: usize, width: usize) -> Vec<T> {
    let mut table = vec![T::zero(); num_tris * width];
    for r in runs {
        for (&tri, sums) in r.tris.iter().zip(r.sums.chunks_exact(width)) {
            let row = &mut table[tri as usize * width..(tri as usize + 1) * width];
            for (t, s) in row.iter_mut().zip(sums) {
                *t += *s;
            }
        }
    }
    table
}
