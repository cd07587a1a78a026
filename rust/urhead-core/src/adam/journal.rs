//! The undo journal of sparse Adam steps: the values every row had before the first step
//! that changed it since the journal was last cleared, so a caller that finds a step (or a
//! run of steps) bad can put the table back exactly.
//!
//! Rows are saved by the step itself, in its own pass, just before it writes them (the row
//! is in cache then), so a journal costs one copy per distinct row per window (not per
//! step) and never a second table. Its buffers keep their capacity across `clear`s.

use std::mem::MaybeUninit;

use rayon::prelude::*;

use super::{Moment, SparseAdamState};
use crate::error::{check_len, Error, Result};

/// Saved rows of one `(N, C)` table and its Adam state (moments stored as `M`).
#[derive(Debug, Clone)]
pub struct RowJournal<M: Moment = f32> {
    channels: usize,
    /// `(N,)` whether a row is already saved.
    saved: Vec<bool>,
    /// `(K,)` saved rows, in the order they were saved.
    rows: Vec<i64>,
    /// `(K, C)` their parameters and moments, `(K,)` their step counts.
    param: Vec<f32>,
    exp_avg: Vec<M>,
    exp_avg_sq: Vec<M>,
    steps: Vec<i32>,
}

impl<M: Moment> RowJournal<M> {
    /// An empty journal for a table of `rows` rows of `channels` channels.
    pub fn new(rows: usize, channels: usize) -> Self {
        Self {
            channels,
            saved: vec![false; rows],
            rows: Vec::new(),
            param: Vec::new(),
            exp_avg: Vec::new(),
            exp_avg_sq: Vec::new(),
            steps: Vec::new(),
        }
    }

    /// Number of rows saved since the last clear.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Forgets the saved rows (the table's current state becomes the one to go back to).
    /// Costs O(saved rows), not O(N).
    pub fn clear(&mut self) {
        for &row in &self.rows {
            self.saved[row as usize] = false;
        }
        self.rows.clear();
        self.param.clear();
        self.exp_avg.clear();
        self.exp_avg_sq.clear();
        self.steps.clear();
    }

    /// Checks that `state` is the table this journal was made for.
    pub(super) fn check(&self, state: &SparseAdamState<'_, M>) -> Result<()> {
        let (n, c) = (self.saved.len(), self.channels);
        if state.channels != c || state.steps.len() != n {
            return Err(Error::Shape {
                arg: "journal",
                expected: format!(
                    "a journal of the table's ({}, {}) rows",
                    state.steps.len(),
                    state.channels
                ),
                got: format!("one of ({n}, {c})"),
            });
        }
        Ok(())
    }

    /// Marks the rows of `rows` not saved since the last clear as saved and returns which
    /// of `rows` they are, with free space for their values: the step writes each one's
    /// row into its slot before changing it, then [`RowJournal::commit`] counts them in.
    pub(super) fn reserve(&mut self, rows: &[i64]) -> Result<(Vec<bool>, SaveSlots<'_, M>)> {
        let new = self.mark_saved(rows);
        let count = new.par_iter().filter(|&&n| n).count();
        let c = self.channels;
        let row_bytes = 4 + 2 * std::mem::size_of::<M>();
        let too_large = |what| Error::OutOfMemory {
            what,
            elements: count * c,
            bytes: (count * c * row_bytes) as u128,
        };
        self.rows
            .try_reserve(count)
            .map_err(|_| too_large("journal rows"))?;
        self.rows
            .par_extend(rows.par_iter().zip(&new).filter(|(_, &n)| n).map(|(&r, _)| r));
        self.param
            .try_reserve(count * c)
            .map_err(|_| too_large("journal"))?;
        for table in [&mut self.exp_avg, &mut self.exp_avg_sq] {
            table.try_reserve(count * c).map_err(|_| too_large("journal"))?;
        }
        self.steps
            .try_reserve(count)
            .map_err(|_| too_large("journal steps"))?;
        let slots = SaveSlots {
            param: &mut self.param.spare_capacity_mut()[..count * c],
            exp_avg: &mut self.exp_avg.spare_capacity_mut()[..count * c],
            exp_avg_sq: &mut self.exp_avg_sq.spare_capacity_mut()[..count * c],
            steps: &mut self.steps.spare_capacity_mut()[..count],
        };
        Ok((new, slots))
    }

    /// Marks `rows` (strictly increasing, in range) saved; returns which were not. In
    /// parallel over chunks of rows, each owning the slice of `saved` up to its last row
    /// (a serial pass over a step's ~350k rows left the pool's other worker idle).
    fn mark_saved(&mut self, rows: &[i64]) -> Vec<bool> {
        const CHUNK: usize = 16_384;
        let mut new = vec![false; rows.len()];
        let mut work = Vec::with_capacity(rows.len().div_ceil(CHUNK));
        let (mut saved, mut base) = (&mut self.saved[..], 0usize);
        for (chunk, out) in rows.chunks(CHUNK).zip(new.chunks_mut(CHUNK)) {
            let end = *chunk.last().expect("chunks are non-empty") as usize + 1;
            let (head, tail) = std::mem::take(&mut saved).split_at_mut(end - base);
            work.push((chunk, out, head, base));
            (saved, base) = (tail, end);
        }
        work.into_par_iter().for_each(|(chunk, out, saved, base)| {
            for (was_new, &row) in out.iter_mut().zip(chunk) {
                *was_new = !std::mem::replace(&mut saved[row as usize - base], true);
            }
        });
        new
    }

    /// Counts in the `count` rows [`RowJournal::reserve`] handed out, once all are written.
    ///
    /// # Safety
    /// The first `count` slots of each table the last `reserve` returned are initialised.
    pub(super) unsafe fn commit(&mut self, count: usize) {
        let c = self.channels;
        // SAFETY: the caller wrote those slots, which lie within the reserved capacity.
        unsafe {
            self.param.set_len(self.param.len() + count * c);
            self.exp_avg.set_len(self.exp_avg.len() + count * c);
            self.exp_avg_sq.set_len(self.exp_avg_sq.len() + count * c);
            self.steps.set_len(self.steps.len() + count);
        }
    }

    /// Writes the saved rows back into `state`: it is then bit for bit what it was at the
    /// last clear. The journal keeps its rows (restoring twice is harmless).
    pub fn restore(&self, state: &mut SparseAdamState<'_, M>) -> Result<()> {
        self.check(state)?;
        let n = self.saved.len();
        check_len(
            "param",
            state.param,
            n * self.channels,
            "(N, C) of the journal's table",
        )?;
        check_len(
            "exp_avg",
            state.exp_avg,
            n * self.channels,
            "(N, C) of the journal's table",
        )?;
        check_len(
            "exp_avg_sq",
            state.exp_avg_sq,
            n * self.channels,
            "(N, C) of the journal's table",
        )?;
        let c = self.channels;
        for (k, &row) in self.rows.iter().enumerate() {
            let (r, saved) = (row as usize, k * c..(k + 1) * c);
            state.param[r * c..(r + 1) * c].copy_from_slice(&self.param[saved.clone()]);
            state.exp_avg[r * c..(r + 1) * c].copy_from_slice(&self.exp_avg[saved.clone()]);
            state.exp_avg_sq[r * c..(r + 1) * c].copy_from_slice(&self.exp_avg_sq[saved]);
            state.steps[r] = self.steps[k];
        }
        Ok(())
    }
}

/// Free space for rows a step saves: `(K, C)` parameters and moments, `(K,)` step counts.
pub(super) struct SaveSlots<'a, M> {
    pub param: &'a mut [MaybeUninit<f32>],
    pub exp_avg: &'a mut [MaybeUninit<M>],
    pub exp_avg_sq: &'a mut [MaybeUninit<M>],
    pub steps: &'a mut [MaybeUninit<i32>],
}

/// Splits the first `len` slots off the front of `slots`.
fn take_front<'a, T>(slots: &mut &'a mut [MaybeUninit<T>], len: usize) -> &'a mut [MaybeUninit<T>] {
    let (head, tail) = std::mem::take(slots).split_at_mut(len);
    *slots = tail;
    head
}

/// Writes `row` into `slots` (of the same length).
fn write_row<T: Copy>(slots: &mut [MaybeUninit<T>], row: &[T]) {
    for (slot, &x) in slots.iter_mut().zip(row) {
        slot.write(x);
    }
}

impl<'a, M: Moment> SaveSlots<'a, M> {
    /// Splits off the first `rows` rows' slots.
    pub fn split_off_front(&mut self, rows: usize, channels: usize) -> SaveSlots<'a, M> {
        let len = rows * channels;
        SaveSlots {
            param: take_front(&mut self.param, len),
            exp_avg: take_front(&mut self.exp_avg, len),
            exp_avg_sq: take_front(&mut self.exp_avg_sq, len),
            steps: take_front(&mut self.steps, rows),
        }
    }

    /// Writes one row into slot `k`.
    pub fn write(&mut self, k: usize, param: &[f32], exp_avg: &[M], exp_avg_sq: &[M], steps: i32) {
        let slots = k * param.len()..(k + 1) * param.len();
        write_row(&mut self.param[slots.clone()], param);
        write_row(&mut self.exp_avg[slots.clone()], exp_avg);
        write_row(&mut self.exp_avg_sq[slots], exp_avg_sq);
        self.steps[k].write(steps);
    }
}
