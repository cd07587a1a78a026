//! The undo journal of sparse Adam steps: the values every row had before the first step
//! that changed it since the journal was last cleared, so a caller that finds a step (or a
//! run of steps) bad can put the table back exactly.
//!
//! Rows are saved by the step itself, just before it writes them, so a journal costs one
//! copy per distinct row per window (not per step) and never a second table. Its buffers
//! keep their capacity across `clear`s.

use super::SparseAdamState;
use crate::error::{check_len, Error, Result};

/// Saved rows of one `(N, C)` table and its Adam state.
#[derive(Debug, Clone)]
pub struct RowJournal {
    channels: usize,
    /// `(N,)` whether a row is already saved.
    saved: Vec<bool>,
    /// `(K,)` saved rows, in the order they were saved.
    rows: Vec<i64>,
    /// `(K, C)` their parameters and moments, `(K,)` their step counts.
    param: Vec<f32>,
    exp_avg: Vec<f32>,
    exp_avg_sq: Vec<f32>,
    steps: Vec<i32>,
}

impl RowJournal {
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
    pub(super) fn check(&self, state: &SparseAdamState<'_>) -> Result<()> {
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

    /// Saves the rows of `rows` not saved yet, as they are in `state` now.
    pub(super) fn save(&mut self, state: &SparseAdamState<'_>, rows: &[i64]) {
        let c = self.channels;
        for &row in rows {
            let r = row as usize;
            if std::mem::replace(&mut self.saved[r], true) {
                continue;
            }
            self.rows.push(row);
            self.param.extend_from_slice(&state.param[r * c..(r + 1) * c]);
            self.exp_avg.extend_from_slice(&state.exp_avg[r * c..(r + 1) * c]);
            self.exp_avg_sq
                .extend_from_slice(&state.exp_avg_sq[r * c..(r + 1) * c]);
            self.steps.push(state.steps[r]);
        }
    }

    /// Writes the saved rows back into `state`: it is then bit for bit what it was at the
    /// last clear. The journal keeps its rows (restoring twice is harmless).
    pub fn restore(&self, state: &mut SparseAdamState<'_>) -> Result<()> {
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
