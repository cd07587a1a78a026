//! Sparse ("lazy") Adam over the rows of a `(N, C)` parameter table: only rows that
//! received a gradient are read or written, so a step costs O(touched rows · C), never a
//! pass over the whole table (a 2048² × 56 UV atlas is 235M floats).
//!
//! Per-row step counts give each texel its own bias correction, so a texel first touched
//! at iteration 10 000 takes a properly sized first step (a global count would make its
//! first steps ~√(1 − β2^t)/(1 − β1^t)-mis-scaled). Per-channel learning rates let one
//! table hold maps with different rates (colour, normal, scale, opacity, displacement).
//!
//! Robustness (NUMERICS.md): a row whose gradient holds NaN or infinity is rejected whole
//! (moments, count and parameter untouched) and counted; rows with |g| > 1e18 update in
//! f64 so g² cannot overflow; every step is clamped to lr·max(1, (1 − β1)/√(1 − β2)), the bound
//! an exact Adam step satisfies.
//!
//! For a caller that judges steps (the trainer's step guard), a step reports what it saw:
//! each channel's largest gradient, the rows it rejected and any row whose update came out
//! non-finite; with a [`RowJournal`] it also saves every row before first changing it, so a
//! bad step (or window of steps) can be undone bit for bit. All of it is gathered in the
//! step's own pass over the rows, where the data is already in cache.
//!
//! A texture table's gradient can also come unsummed, as the entries of its lookups
//! ([`sparse_adam_step_sampled`]): each texel's row is summed as the step reaches it, so a
//! fit never stores (or pages in) the `(K, C)` gradient and reads it back.

mod journal;
mod moments;

use rayon::prelude::*;

pub use journal::RowJournal;
use journal::SaveSlots;
use moments::{row_seed, ChannelBits};
pub use moments::{Bf16, Moment};

use crate::error::{check_indices, check_len, first_pair_where, Error, Result};
use crate::memory::prefetch;
use crate::raster::TexelEntries;

/// Rows handled per parallel work item.
const ROW_CHUNK: usize = 256;

/// Hyper-parameters of one step.
#[derive(Debug, Clone, Copy)]
pub struct AdamConfig {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

impl AdamConfig {
    fn validate(&self) -> Result<()> {
        let invalid = |arg, reason: String| Err(Error::Invalid { arg, reason });
        if !(0.0..1.0).contains(&self.beta1) {
            return invalid("beta1", format!("must be in [0, 1), got {}", self.beta1));
        }
        if !(0.0..1.0).contains(&self.beta2) {
            return invalid("beta2", format!("must be in [0, 1), got {}", self.beta2));
        }
        if !(self.eps > 0.0 && self.eps.is_finite()) {
            return invalid("eps", format!("must be positive and finite, got {}", self.eps));
        }
        Ok(())
    }

    /// Largest step magnitude per unit learning rate.
    fn step_bound(&self) -> f64 {
        1f64.max((1.0 - self.beta1) / (1.0 - self.beta2).sqrt())
    }
}

/// The optimiser state of one table, borrowed mutably for a step. The moments are `f32`
/// or [`Bf16`] (see [`Moment`]); the parameters are always `f32`.
#[derive(Debug)]
pub struct SparseAdamState<'a, M: Moment = f32> {
    /// `(N, C)` parameters.
    pub param: &'a mut [f32],
    /// `(N, C)` first moments.
    pub exp_avg: &'a mut [M],
    /// `(N, C)` second moments.
    pub exp_avg_sq: &'a mut [M],
    /// `(N,)` number of accepted steps of each row.
    pub steps: &'a mut [i32],
    pub channels: usize,
}

/// What one step saw and did.
#[derive(Debug, Clone, PartialEq)]
pub struct StepReport {
    /// Rows skipped whole for a NaN or infinite gradient entry.
    pub rejected_rows: usize,
    /// Rows whose updated parameters or moments came out NaN or infinite (possible only for
    /// values near f32::MAX); they are written, and saved first when a journal is given.
    pub non_finite_rows: usize,
    /// `(C,)` each channel's largest gradient magnitude over the step's rows; +∞ for a
    /// channel with a NaN or infinite entry, 0 for no rows.
    pub peaks: Vec<f32>,
    /// Rows saved into the journal by this step (first changed since its last clear).
    pub saved_rows: usize,
}

/// One sparse step. `rows (K,)` must be strictly increasing row indices (a coalesced
/// sparse gradient), `grads (K, C)` their gradients, `lr (C,)` per-channel rates. With a
/// `journal`, every row not yet in it is saved before the step writes it.
pub fn sparse_adam_step<M: Moment>(
    state: &mut SparseAdamState<'_, M>,
    rows: &[i64],
    grads: &[f32],
    lr: &[f32],
    config: &AdamConfig,
    journal: Option<&mut RowJournal<M>>,
) -> Result<StepReport> {
    let c = state.channels;
    check_len(
        "grads",
        grads,
        rows.len() * c,
        &format!("(K, C) = ({}, {c})", rows.len()),
    )?;
    step_rows(
        state,
        rows,
        &StoredRows { grads, channels: c },
        lr,
        config,
        journal,
    )
}

/// One sparse step of a table that is a texture `(Ht, Wt, C)` (rows are texels, row-major),
/// its gradient given as the unsummed entries of texture lookups' output gradients
/// ([`texture_gradient_entries`](crate::raster::texture_gradient_entries)): each texel's
/// row is summed as the step reaches it, so the `(K, C)` gradient is never stored. The same
/// result, bit for bit, as [`sparse_adam_step`] on the coalesced gradient
/// ([`texture_backward`](crate::raster::texture_backward)) of the same lookups.
pub fn sparse_adam_step_sampled<M: Moment>(
    state: &mut SparseAdamState<'_, M>,
    texels: &TexelEntries<'_, f32>,
    lr: &[f32],
    config: &AdamConfig,
    journal: Option<&mut RowJournal<M>>,
) -> Result<StepReport> {
    let (c, n) = (state.channels, state.param.len() / state.channels.max(1));
    if texels.channels() != c || texels.texel_count() != n {
        return Err(Error::Shape {
            arg: "texels",
            expected: format!("entries of a texture of the table's {n} rows × {c} channels"),
            got: format!("{} texels × {} channels", texels.texel_count(), texels.channels()),
        });
    }
    let rows: Vec<i64> = (0..texels.len())
        .into_par_iter()
        .map(|k| texels.texel(k) as i64)
        .collect();
    step_rows(state, &rows, texels, lr, config, journal)
}

/// Where a step's gradient rows come from.
trait RowGradients: Sync {
    /// Row `k`'s gradient `(C,)`: stored, or summed into `scratch`.
    fn row<'a>(&'a self, k: usize, scratch: &'a mut [f32]) -> &'a [f32];
    /// Starts loading what row `k` reads, if it is not stored in order.
    fn prefetch(&self, _k: usize) {}
}

/// A coalesced gradient's values `(K, C)`.
struct StoredRows<'a> {
    grads: &'a [f32],
    channels: usize,
}

impl RowGradients for StoredRows<'_> {
    #[inline(always)]
    fn row<'a>(&'a self, k: usize, _scratch: &'a mut [f32]) -> &'a [f32] {
        &self.grads[k * self.channels..(k + 1) * self.channels]
    }
}

/// Texture lookups' output gradients, summed per texel.
impl RowGradients for TexelEntries<'_, f32> {
    #[inline(always)]
    fn row<'a>(&'a self, k: usize, scratch: &'a mut [f32]) -> &'a [f32] {
        self.sum_into(k, scratch);
        scratch
    }

    #[inline(always)]
    fn prefetch(&self, k: usize) {
        TexelEntries::prefetch(self, k); // the inherent method
    }
}

/// The step over `rows` (validated here) with each row's gradient from `grads`.
fn step_rows<M: Moment, G: RowGradients>(
    state: &mut SparseAdamState<'_, M>,
    rows: &[i64],
    grads: &G,
    lr: &[f32],
    config: &AdamConfig,
    journal: Option<&mut RowJournal<M>>,
) -> Result<StepReport> {
    let c = state.channels;
    if c == 0 {
        return Err(Error::Shape {
            arg: "param",
            expected: "(N, C) with C >= 1".into(),
            got: "C = 0".into(),
        });
    }
    let n = state.param.len() / c;
    check_len("param", state.param, n * c, &format!("(N, C) with C = {c}"))?;
    check_len("exp_avg", state.exp_avg, n * c, &format!("(N, C) = ({n}, {c})"))?;
    check_len(
        "exp_avg_sq",
        state.exp_avg_sq,
        n * c,
        &format!("(N, C) = ({n}, {c})"),
    )?;
    check_len("steps", state.steps, n, &format!("(N,) = ({n},)"))?;
    check_len("lr", lr, c, &format!("(C,) = ({c},)"))?;
    config.validate()?;
    if let Some(i) = lr.iter().position(|x| !(*x >= 0.0 && x.is_finite())) {
        return Err(Error::Invalid {
            arg: "lr",
            reason: format!("must be finite and >= 0, got {} at channel {i}", lr[i]),
        });
    }
    // One scan, in parallel blocks (a serial pass over a step's ~350k rows left the pool's
    // other worker idle): strictly increasing rows are all in range when their ends are, so
    // the range scan runs only to name the first bad row (a range error comes first).
    let unordered = first_pair_where(rows, |a, b| b <= a);
    let ends = [rows.first(), rows.last()];
    if unordered.is_some() || ends.iter().flatten().any(|&&r| !(0..n as i64).contains(&r)) {
        check_indices("rows", rows, 0, n as i64)?;
    }
    if let Some(i) = unordered {
        return Err(Error::Invalid {
            arg: "rows",
            reason: format!(
                "must be strictly increasing (a coalesced gradient), got {} then {} at {i}",
                rows[i - 1],
                rows[i]
            ),
        });
    }
    let mut saving = match journal {
        Some(journal) => {
            journal.check(state)?;
            Some(journal)
        }
        None => None,
    };
    let (new_rows, mut slots) = match saving.as_deref_mut() {
        Some(journal) => {
            let (new, slots) = journal.reserve(rows)?;
            (new, Some(slots))
        }
        None => (Vec::new(), None),
    };

    // Rows are strictly increasing, so each chunk of `rows` owns a disjoint, ordered set
    // of table rows; split the tables at the chunk boundaries to hand them out safely.
    let mut work = Vec::new();
    let (mut param, mut m, mut v, mut steps) = (
        &mut state.param[..],
        &mut state.exp_avg[..],
        &mut state.exp_avg_sq[..],
        &mut state.steps[..],
    );
    let mut offset = 0usize;
    for (k, chunk) in rows.chunks(ROW_CHUNK).enumerate() {
        let end = *chunk.last().expect("chunks are non-empty") as usize + 1;
        let split = end - offset;
        let (p_head, p_tail) = std::mem::take(&mut param).split_at_mut(split * c);
        let (m_head, m_tail) = std::mem::take(&mut m).split_at_mut(split * c);
        let (v_head, v_tail) = std::mem::take(&mut v).split_at_mut(split * c);
        let (s_head, s_tail) = std::mem::take(&mut steps).split_at_mut(split);
        let saves = slots.as_mut().map(|slots| {
            let new = &new_rows[k * ROW_CHUNK..k * ROW_CHUNK + chunk.len()];
            (new, slots.split_off_front(new.iter().filter(|&&n| n).count(), c))
        });
        work.push((k, offset, chunk, p_head, m_head, v_head, s_head, saves));
        (param, m, v, steps) = (p_tail, m_tail, v_tail, s_tail);
        offset = end;
    }
    let chunk_reports = work.into_par_iter().map(|(k, base, chunk, p, m, v, s, saves)| {
        step_chunk(chunk, base, p, m, v, s, saves, grads, k * ROW_CHUNK, lr, config)
    });
    let empty = || StepReport {
        rejected_rows: 0,
        non_finite_rows: 0,
        peaks: vec![0.0; c],
        saved_rows: 0,
    };
    let report = chunk_reports.reduce(empty, |mut a, b| {
        a.rejected_rows += b.rejected_rows;
        a.non_finite_rows += b.non_finite_rows;
        a.saved_rows += b.saved_rows;
        for (x, y) in a.peaks.iter_mut().zip(&b.peaks) {
            *x = x.max(*y);
        }
        a
    });
    if let Some(journal) = saving {
        let reserved = new_rows.iter().filter(|&&n| n).count();
        assert_eq!(
            report.saved_rows, reserved,
            "every reserved journal slot is written"
        );
        // SAFETY: each chunk wrote one slot per new row of its own, and the chunks' slot
        // ranges partition the reserved ones in order; the counts agree (asserted).
        unsafe { journal.commit(reserved) };
    }
    Ok(report)
}

/// Rows ahead of the one being updated whose table lines are prefetched. Touched rows are
/// sorted but scattered over the atlas (at 2048² about half are not adjacent to the last),
/// so without it each row stalls on its ~11 cache misses in turn (measured on the paper's
/// iteration's 348k rows: 160 → ~90 ms on one thread). 8 rows ahead rather than 16 since
/// the moments are bfloat16 (a row is 7 lines, not 11): on a real iteration's step, 30
/// alternating pairs each, 16 → 8 −2.4 ms (of 33) paired, 8 → 4 and 8 → 12 within ±1 ms,
/// and with float32 moments 16 → 8 −0.3 ms.
const PREFETCH_ROWS: usize = 8;

/// One chunk's rows: `chunk` holds table rows (strictly increasing, all ≥ `base`), the
/// tables are views starting at row `base`, row `i` of the chunk has gradient row
/// `first + i` of `grads`. With `saves`, the rows flagged new are written, as they are
/// before this step, into the slots in order.
#[allow(clippy::too_many_arguments)]
fn step_chunk<M: Moment, G: RowGradients>(
    chunk: &[i64],
    base: usize,
    p: &mut [f32],
    m: &mut [M],
    v: &mut [M],
    s: &mut [i32],
    mut saves: Option<(&[bool], SaveSlots<'_, M>)>,
    grads: &G,
    first: usize,
    lr: &[f32],
    config: &AdamConfig,
) -> StepReport {
    let c = lr.len();
    let mut report = StepReport {
        rejected_rows: 0,
        non_finite_rows: 0,
        peaks: vec![0.0; c],
        saved_rows: 0,
    };
    let mut scratch = vec![0f32; c];
    let mut peak_bits = vec![0u32; c];
    let mut corrections = BiasCorrections::new(config);
    let channel_bits = ChannelBits::new(c);
    for (i, &row) in chunk.iter().enumerate() {
        if let Some(&ahead) = chunk.get(i + PREFETCH_ROWS) {
            let r = ahead as usize - base;
            prefetch(&p[r * c..(r + 1) * c]);
            prefetch(&m[r * c..(r + 1) * c]);
            prefetch(&v[r * c..(r + 1) * c]);
            prefetch(&s[r..r + 1]);
            grads.prefetch(first + i + PREFETCH_ROWS);
        }
        let g = grads.row(first + i, &mut scratch);
        let local = row as usize - base;
        let rows = local * c..(local + 1) * c;
        if let Some((new, slots)) = saves.as_mut() {
            if new[i] {
                let (p, m, v) = (&p[rows.clone()], &m[rows.clone()], &v[rows.clone()]);
                slots.write(report.saved_rows, p, m, v, s[local]);
                report.saved_rows += 1;
            }
        }
        // One pass: each channel's peak, and whether every entry is small enough for the
        // f32 update, on magnitude bits (see `magnitude_bits`): integer maxima vectorise
        // without `f32::max`'s NaN handling, and NaN and ±∞ are larger than any finite value.
        let mut largest = 0u32;
        for (peak, x) in peak_bits.iter_mut().zip(g) {
            let bits = magnitude_bits(*x);
            *peak = (*peak).max(bits);
            largest = largest.max(bits);
        }
        let small = largest <= F32_SAFE_GRAD.to_bits();
        if !small && g.iter().any(|x| !x.is_finite()) {
            report.rejected_rows += 1;
            continue;
        }
        let t = s[local].saturating_add(1);
        s[local] = t;
        let (p, m, v) = (&mut p[rows.clone()], &mut m[rows.clone()], &mut v[rows]);
        let finite = if small {
            let seed = row_seed(row as u64, t);
            let random = (ChannelBits::row_part(seed), channel_bits.parts());
            update_row_f32(p, m, v, g, lr, corrections.at(t), config, random)
        } else {
            update_row_f64(p, m, v, g, lr, t, config);
            let moments = m.iter().chain(v.iter()).map(|x| x.load());
            p.iter().copied().chain(moments).all(f32::is_finite)
        };
        if !finite {
            report.non_finite_rows += 1;
        }
    }
    // NaN's bits lie above ∞'s: a channel that saw one peaks at +∞.
    for (peak, bits) in report.peaks.iter_mut().zip(peak_bits) {
        *peak = f32::from_bits(bits.min(f32::INFINITY.to_bits()));
    }
    report
}

/// Gradients up to this magnitude square safely in f32 (g² ≤ 1e36 < f32::MAX).
const F32_SAFE_GRAD: f32 = 1e18;

/// `1 / (1 − β1^t)` and `1 / √(1 − β2^t)` in f32 for a row's step count `t`, kept in a
/// small direct-mapped table: the rows of a chunk were first touched in a handful of
/// steps, so few distinct counts occur and the two `powi` per row (~1.6 % of a fit
/// step's CPU time when made per row) are made once per count.
struct BiasCorrections<'a> {
    config: &'a AdamConfig,
    slots: [(i32, (f32, f32)); CORRECTION_SLOTS],
}

const CORRECTION_SLOTS: usize = 64;

impl<'a> BiasCorrections<'a> {
    fn new(config: &'a AdamConfig) -> Self {
        Self {
            config,
            // No row steps with t = 0 (the first step has t = 1): every slot starts empty.
            slots: [(0, (f32::NAN, f32::NAN)); CORRECTION_SLOTS],
        }
    }

    #[inline(always)]
    fn at(&mut self, t: i32) -> (f32, f32) {
        let slot = &mut self.slots[t as usize % CORRECTION_SLOTS];
        if slot.0 != t {
            let (b1, b2) = (self.config.beta1, self.config.beta2);
            *slot = (
                t,
                (
                    (1.0 / (1.0 - b1.powi(t))) as f32,
                    (1.0 / (1.0 - b2.powi(t)).sqrt()) as f32,
                ),
            );
        }
        slot.1
    }
}

/// The common case, in f32 (vectorises), with the row's inverse bias corrections
/// (see [`BiasCorrections`]). The step uses the moments as computed; only their stored
/// copies are rounded, the second stochastically with the bits `random` gives (a row part
/// and the channels' parts, see [`ChannelBits`]).
///
/// They are rounded without a NaN test (a compare and a blend per vector of each: the
/// maps' step alone −2.2 ms paired on a real step, faster in 86 of 100). The gradient is
/// finite and β ∈ [0, 1), so a new moment is NaN only where its stored one is: with finite
/// moments each is a sum of two finite products, finite or ±∞, and rounds exactly as with
/// the test. A NaN moment makes the channel's step NaN, so its parameter turns NaN and the
/// row is reported non-finite as before; only what such a row's moments are rounded to
/// (NaN, or another non-finite or wrapped value) is left unspecified.
#[allow(clippy::too_many_arguments)]
fn update_row_f32<M: Moment>(
    p: &mut [f32],
    m: &mut [M],
    v: &mut [M],
    g: &[f32],
    lr: &[f32],
    (inv_correction1, inv_sqrt_correction2): (f32, f32),
    config: &AdamConfig,
    (row_part, channel_parts): (u32, &[u32]),
) -> bool {
    // 1 − β in f64 first: 1 − 0.999f32 is off by 1.3e-5 relative in f32.
    let (b1, b2) = (config.beta1 as f32, config.beta2 as f32);
    let (one_minus_b1, one_minus_b2) = ((1.0 - config.beta1) as f32, (1.0 - config.beta2) as f32);
    let (eps, bound) = (config.eps as f32, config.step_bound() as f32);
    // The row's finiteness, in the update's own pass: the largest magnitude's bits (an
    // unsigned max, which vectorises as a plain reduction) reach those of ∞ exactly when
    // some value is NaN or ±∞.
    let mut largest = 0u32;
    let rows = p.iter_mut().zip(m).zip(v).zip(g).zip(lr).zip(channel_parts);
    for (((((p, m), v), &g), &lr), &part) in rows {
        let mi = b1 * m.load() + one_minus_b1 * g;
        let vi = b2 * v.load() + one_minus_b2 * g * g;
        let step = (mi * inv_correction1) / (vi.sqrt() * inv_sqrt_correction2 + eps);
        *m = M::round_nearest_not_nan(mi);
        *v = M::round_stochastic_not_nan(vi, ChannelBits::random(row_part, part));
        *p -= step.clamp(-bound, bound) * lr;
        largest = largest
            .max(magnitude_bits(mi))
            .max(magnitude_bits(vi))
            .max(magnitude_bits(*p));
    }
    largest < f32::INFINITY.to_bits()
}

/// `|x|`'s bits: ordered as the magnitudes are, with NaNs above ∞.
#[inline(always)]
fn magnitude_bits(x: f32) -> u32 {
    x.to_bits() & 0x7FFF_FFFF
}

/// Rows with huge gradients, in f64 so g² cannot overflow; the second moment saturates
/// at the largest finite moment rather than becoming infinite (both rounded to nearest:
/// the path is rare, and a saturated `v` decays by more than a spacing a step).
fn update_row_f64<M: Moment>(
    p: &mut [f32],
    m: &mut [M],
    v: &mut [M],
    g: &[f32],
    lr: &[f32],
    t: i32,
    config: &AdamConfig,
) {
    let correction1 = 1.0 - config.beta1.powi(t);
    let correction2 = 1.0 - config.beta2.powi(t);
    let bound = config.step_bound();
    for ch in 0..g.len() {
        let gi = g[ch] as f64;
        let mi = config.beta1 * m[ch].load() as f64 + (1.0 - config.beta1) * gi;
        let vi = config.beta2 * v[ch].load() as f64 + (1.0 - config.beta2) * gi * gi;
        let step = (mi / correction1) / ((vi / correction2).sqrt() + config.eps);
        m[ch] = M::round_nearest(mi as f32);
        v[ch] = M::round_nearest(vi.min(M::MAX as f64) as f32);
        p[ch] = (p[ch] as f64 - step.clamp(-bound, bound) * lr[ch] as f64) as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CONFIG: AdamConfig = AdamConfig {
        beta1: 0.9,
        beta2: 0.999,
        eps: 1e-15,
    };

    #[test]
    fn kept_bias_corrections_are_the_ones_computed_per_row() {
        let mut kept = BiasCorrections::new(&CONFIG);
        // Counts that share slots (t and t + 64), repeat, and come back after eviction.
        for t in [1, 65, 1, 2, 2, 129, 1, 50_000, 7, 65, i32::MAX] {
            let expected = (
                (1.0 / (1.0 - CONFIG.beta1.powi(t))) as f32,
                (1.0 / (1.0 - CONFIG.beta2.powi(t)).sqrt()) as f32,
            );
            let got = kept.at(t);
            assert_eq!(
                (got.0.to_bits(), got.1.to_bits()),
                (expected.0.to_bits(), expected.1.to_bits()),
                "t = {t}"
            );
        }
    }

    fn state(n: usize, c: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<i32>) {
        (
            (0..n * c).map(|i| i as f32 * 0.25).collect(),
            vec![0.0; n * c],
            vec![0.0; n * c],
            vec![0; n],
        )
    }

    /// Parameters, both moments (stored as `M`) and step counts.
    type Tables<M = f32> = (Vec<f32>, Vec<M>, Vec<M>, Vec<i32>);

    fn as_state<M: Moment>(tables: &mut Tables<M>, channels: usize) -> SparseAdamState<'_, M> {
        let (param, exp_avg, exp_avg_sq, steps) = tables;
        SparseAdamState {
            param,
            exp_avg,
            exp_avg_sq,
            steps,
            channels,
        }
    }

    /// Lookups split into segments — one, several, empty ones, splits inside and on
    /// sample-chunk boundaries: the step on their entries is bit for bit the step on the
    /// coalesced gradient of their concatenation, on 1, 2 and 3 threads.
    #[test]
    fn a_step_on_texture_entries_is_the_step_on_the_built_gradient() {
        use crate::raster::{texture_backward, texture_gradient_entries, TextureSamples};
        use crate::testing::{on_threads, Rng};
        let (h, w, c) = (23, 17, 3);
        let n = 5000; // ~50 entries a texel, from every segment
        let lr = [0.1, 0.01, 0.001];
        let mut rng = Rng::new(11);
        let uv: Vec<f32> = rng.vec(2 * n, -0.05, 1.05);
        let mut v_out: Vec<f32> = rng.vec(n * c, -1.0, 1.0);
        v_out[7 * c + 1] = f32::NAN; // rejects the texels sample 7 reaches
        v_out[40 * c..41 * c].fill(0.0); // no gradient: no entries
        let tables = state(h * w, c);
        let mut built = tables.clone();
        let grad = texture_backward(&built.0, h, w, c, &uv, &v_out, true, false)
            .unwrap()
            .v_tex
            .unwrap();
        let rows: Vec<i64> = (0..grad.nnz)
            .map(|k| grad.indices[k] * w as i64 + grad.indices[grad.nnz + k])
            .collect();
        let mut built_journal = RowJournal::new(h * w, c);
        let expected = sparse_adam_step(
            &mut as_state(&mut built, c),
            &rows,
            &grad.values,
            &lr,
            &CONFIG,
            Some(&mut built_journal),
        )
        .unwrap();
        assert!(expected.rejected_rows > 0);
        let bits = |t: &[f32]| t.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let splits: [&[usize]; 5] = [
            &[n],
            &[0, n, 0],
            &[2048, n - 2048],
            &[1, 2047, 0, 2049, n - 4097],
            &[1700, 1700, 0, n - 3400],
        ];
        for lengths in splits {
            let mut first = 0;
            let segments: Vec<TextureSamples<f32>> = lengths
                .iter()
                .map(|&len| {
                    let samples = first..first + len;
                    first += len;
                    TextureSamples {
                        uv: &uv[2 * samples.start..2 * samples.end],
                        v_out: &v_out[c * samples.start..c * samples.end],
                    }
                })
                .collect();
            for threads in [1, 2, 3] {
                let mut sampled = tables.clone();
                let mut journal = RowJournal::new(h * w, c);
                let (texels, report) = on_threads(threads, || {
                    let texels = texture_gradient_entries(h, w, c, &segments).unwrap();
                    let mut st = as_state(&mut sampled, c);
                    let report = sparse_adam_step_sampled(&mut st, &texels, &lr, &CONFIG, Some(&mut journal));
                    (texels.len(), report.unwrap())
                });
                let case = format!("segments {lengths:?} on {threads} threads");
                assert_eq!(report, expected, "{case}");
                assert_eq!(texels, grad.nnz, "{case}");
                assert_eq!(bits(&sampled.0), bits(&built.0), "{case}");
                assert_eq!(bits(&sampled.1), bits(&built.1), "{case}");
                assert_eq!(bits(&sampled.2), bits(&built.2), "{case}");
                assert_eq!(sampled.3, built.3, "{case}");
                assert_eq!(format!("{journal:?}"), format!("{built_journal:?}"), "{case}");
            }
        }
    }

    #[test]
    fn texture_entries_of_another_table_are_refused() {
        use crate::raster::{texture_gradient_entries, TextureSamples};
        let segment = TextureSamples {
            uv: &[0.5f32, 0.5],
            v_out: &[1.0, 1.0],
        };
        let texels = texture_gradient_entries(4, 4, 2, &[segment]).unwrap();
        let mut tables = state(15, 2);
        let mut st = as_state(&mut tables, 2);
        let err = sparse_adam_step_sampled(&mut st, &texels, &[0.1, 0.1], &CONFIG, None);
        assert!(matches!(err, Err(Error::Shape { arg: "texels", .. })));
    }

    #[test]
    fn texture_segments_of_mismatched_lengths_are_refused() {
        use crate::raster::{texture_gradient_entries, TextureSamples};
        let whole = TextureSamples {
            uv: &[0.5f32, 0.5, 0.25, 0.25],
            v_out: &[1.0, 1.0, 2.0, 2.0],
        };
        let short = TextureSamples {
            uv: &[0.5f32, 0.5, 0.25, 0.25],
            v_out: &[1.0, 1.0],
        };
        let odd = TextureSamples {
            uv: &[0.5f32, 0.5, 0.25],
            v_out: &[1.0, 1.0],
        };
        for bad in [short, odd] {
            let err = texture_gradient_entries(4, 4, 2, &[whole, bad]).unwrap_err();
            assert!(matches!(&err, Error::Shape { arg: "segments", .. }), "{err}");
            assert!(err.to_string().contains("segment 1"), "{err}");
        }
    }

    #[test]
    fn first_step_moves_by_lr_against_the_gradient_sign() {
        let mut tables = state(10, 2);
        let before = tables.0.clone();
        let mut st = as_state(&mut tables, 2);
        let report = sparse_adam_step(
            &mut st,
            &[3, 7],
            &[2.0, -1e-30, 5.0, 0.0],
            &[0.1, 0.01],
            &CONFIG,
            None,
        )
        .unwrap();
        let (p, _, _, s) = tables;
        assert_eq!((report.rejected_rows, report.non_finite_rows), (0, 0));
        assert_eq!(report.peaks, vec![5.0, 1e-30]);
        assert!((before[6] - p[6] - 0.1).abs() < 1e-6);
        assert_eq!(p[7], before[7]); // |g| = 1e-30 is far below eps: a step of ~1e-17
        assert_eq!(p[15], before[15]); // zero gradient: no move
        assert_eq!(s, vec![0, 0, 0, 1, 0, 0, 0, 1, 0, 0]);
        for row in [0, 1, 2, 4, 5, 6, 8, 9] {
            assert_eq!(p[row * 2..row * 2 + 2], before[row * 2..row * 2 + 2]);
        }
    }

    /// A stored NaN moment (the moments are rounded without a NaN test) still makes its
    /// row's parameter NaN and the row reported non-finite; the other rows step as usual.
    #[test]
    fn a_nan_moment_is_reported_non_finite() {
        for nan_in_first in [true, false] {
            let n = 3;
            let mut tables: Tables<Bf16> = (
                vec![1.0; n * 2],
                vec![Bf16(0); n * 2],
                vec![Bf16(0); n * 2],
                vec![0; n],
            );
            let nan = Bf16(0x7FFF); // a NaN with a full payload: rounding it wraps
            if nan_in_first {
                tables.1[3] = nan;
            } else {
                tables.2[3] = nan;
            }
            let mut st = as_state(&mut tables, 2);
            let report = sparse_adam_step(
                &mut st,
                &[0, 1],
                &[1.0, 1.0, 1.0, 1.0],
                &[0.1, 0.1],
                &CONFIG,
                None,
            )
            .unwrap();
            let p = tables.0;
            assert_eq!((report.rejected_rows, report.non_finite_rows), (0, 1));
            assert!(p[3].is_nan());
            assert!(p[..2].iter().chain(&p[2..3]).all(|x| (x - 0.9).abs() < 1e-6));
        }
    }

    #[test]
    fn rejects_unsorted_and_out_of_range_rows() {
        let (mut p, mut m, mut v, mut s) = state(4, 1);
        let mut st = SparseAdamState {
            param: &mut p,
            exp_avg: &mut m,
            exp_avg_sq: &mut v,
            steps: &mut s,
            channels: 1,
        };
        let err = sparse_adam_step(&mut st, &[2, 1], &[1.0, 1.0], &[0.1], &CONFIG, None).unwrap_err();
        assert!(matches!(err, Error::Invalid { arg: "rows", .. }));
        let err = sparse_adam_step(&mut st, &[4], &[1.0], &[0.1], &CONFIG, None).unwrap_err();
        assert!(matches!(err, Error::IndexOutOfRange { arg: "rows", .. }));
        // The first row out of range is named, in increasing rows and before any disorder.
        let mut out_of_range = |rows: &[i64]| {
            let g = vec![1.0; rows.len()];
            match sparse_adam_step(&mut st, rows, &g, &[0.1], &CONFIG, None) {
                Err(Error::IndexOutOfRange { index, value, .. }) => (index, value),
                other => panic!("{rows:?}: {other:?}"),
            }
        };
        assert_eq!(out_of_range(&[0, 1, 4, 5]), (2, 4));
        assert_eq!(out_of_range(&[-1, 0, 1]), (0, -1));
        assert_eq!(out_of_range(&[3, 1, 7]), (2, 7));
        assert_eq!(out_of_range(&[1, 0, -3, 2]), (2, -3));
    }

    #[test]
    fn a_journal_restores_every_row_its_steps_changed_bit_for_bit() {
        let (mut p, mut m, mut v, mut s) = state(6, 2);
        let before = (p.clone(), m.clone(), v.clone(), s.clone());
        let mut journal = RowJournal::new(6, 2);
        let mut st = SparseAdamState {
            param: &mut p,
            exp_avg: &mut m,
            exp_avg_sq: &mut v,
            steps: &mut s,
            channels: 2,
        };
        let steps: [(&[i64], &[f32]); 3] = [
            (&[1, 4], &[1.0, -2.0, 3.0, 0.5]),
            (&[0, 1], &[f32::NAN, 1.0, 2.0, 2.0]),
            (&[4, 5], &[1e30, 1.0, -1.0, 1.0]),
        ];
        for (rows, grads) in steps {
            sparse_adam_step(&mut st, rows, grads, &[0.1, 0.1], &CONFIG, Some(&mut journal)).unwrap();
        }
        assert_eq!(journal.len(), 4); // rows 1, 4, 0, 5, each saved once
        journal.restore(&mut st).unwrap();
        assert_eq!((p, m, v, s), before);
    }

    /// Steps over many chunks of scattered rows, rows shared between steps, a rejected
    /// row among them: the journal saves each row once, in the order the steps first
    /// reached it, restores the table bit for bit, and tables and journal are the same on
    /// 1, 2 and 5 threads — with either kind of moments (bfloat16's stochastic rounding
    /// draws on the row and its count, not on the thread).
    #[test]
    fn a_journal_over_many_chunks_restores_bit_for_bit_on_any_thread_count() {
        journal_over_many_chunks::<f32>();
        journal_over_many_chunks::<Bf16>();
    }

    fn journal_over_many_chunks<M: Moment + PartialEq>() {
        use crate::testing::{on_threads, Rng};
        let (n, c) = (5000, 7);
        let mut rng = Rng::new(3);
        let step_rows: Vec<Vec<i64>> = (0..3)
            .map(|_| {
                let mut rows: Vec<i64> = (0..n as i64).filter(|_| rng.next_u64() % 3 == 0).collect();
                rows.dedup();
                rows
            })
            .collect();
        let step_grads: Vec<Vec<f32>> = step_rows
            .iter()
            .map(|rows| {
                let mut g = rng.vec::<f32>(rows.len() * c, -1.0, 1.0);
                g[40 * c + 2] = f32::NAN;
                g
            })
            .collect();
        let run = |threads: usize| {
            let (mut p, _, _, mut s) = state(n, c);
            let (mut m, mut v) = (vec![M::default(); n * c], vec![M::default(); n * c]);
            let before = (p.clone(), m.clone(), v.clone(), s.clone());
            let mut journal = RowJournal::<M>::new(n, c);
            let mut st = SparseAdamState {
                param: &mut p,
                exp_avg: &mut m,
                exp_avg_sq: &mut v,
                steps: &mut s,
                channels: c,
            };
            let saved: Vec<usize> = on_threads(threads, || {
                let steps = step_rows.iter().zip(&step_grads);
                steps
                    .map(|(rows, grads)| {
                        let report =
                            sparse_adam_step(&mut st, rows, grads, &[0.1; 7], &CONFIG, Some(&mut journal))
                                .unwrap();
                        assert_eq!(report.rejected_rows, 1);
                        report.saved_rows
                    })
                    .collect()
            });
            let after = (
                st.param.to_vec(),
                st.exp_avg.to_vec(),
                st.exp_avg_sq.to_vec(),
                st.steps.to_vec(),
            );
            journal.restore(&mut st).unwrap();
            assert_eq!((p, m, v, s), before);
            (after, saved, journal)
        };
        let (after, saved, journal) = run(1);
        let mut union: Vec<i64> = step_rows.concat();
        union.sort_unstable();
        union.dedup();
        assert_eq!(journal.len(), union.len());
        assert_eq!(saved[0], step_rows[0].len());
        assert_eq!(saved.iter().sum::<usize>(), union.len());
        for threads in [2, 5] {
            let (after_t, saved_t, journal_t) = run(threads);
            assert!(after_t == after && saved_t == saved, "{threads} threads differ");
            assert_eq!(format!("{journal_t:?}"), format!("{journal:?}"));
        }
    }

    #[test]
    fn a_step_reports_non_finite_gradients_per_channel_and_non_finite_results() {
        let (mut p, mut m, mut v, mut s) = state(3, 3);
        p[3] = f32::MAX;
        let mut st = SparseAdamState {
            param: &mut p,
            exp_avg: &mut m,
            exp_avg_sq: &mut v,
            steps: &mut s,
            channels: 3,
        };
        let grads = [1.0, f32::NAN, -2.0, -1.0, 0.5, 0.25];
        let report = sparse_adam_step(&mut st, &[0, 1], &grads, &[1.0, 1.0, 1.0], &CONFIG, None).unwrap();
        assert_eq!(report.peaks, vec![1.0, f32::INFINITY, 2.0]);
        assert_eq!(report.rejected_rows, 1);
        let report = sparse_adam_step(
            &mut st,
            &[1],
            &[-1.0, 0.0, 0.0],
            &[f32::MAX, 0.0, 0.0],
            &CONFIG,
            None,
        )
        .unwrap();
        assert_eq!(report.non_finite_rows, 1); // f32::MAX + f32::MAX overflows
    }

    /// Each channel's peak is its largest |g| over rows of every kind and every chunk: the
    /// f32 path's, the f64 path's (huge) and the rejected rows' (non-finite, of either sign
    /// and any NaN payload, reported +∞), signed zeros and subnormals included.
    #[test]
    fn peaks_are_each_channels_largest_magnitude_over_all_chunks() {
        let (rows, c) = (3 * ROW_CHUNK + 17, 5);
        let mut rng = crate::testing::Rng::new(7);
        let mut grads: Vec<f32> = rng.vec(rows * c, -2.0, 2.0);
        let specials = [
            -0.0,
            f32::MIN_POSITIVE / 4.0,
            -3e20,
            f32::MAX,
            f32::NEG_INFINITY,
            f32::from_bits(0xFFC0_0001), // a negative NaN with a payload
            f32::NAN,
        ];
        for (k, x) in specials.into_iter().enumerate() {
            grads[(ROW_CHUNK * (k % 3) + 11 * k) * c + k % c] = x;
        }
        let mut tables: Tables = state(rows, c);
        let row_ids: Vec<i64> = (0..rows as i64).collect();
        let report = sparse_adam_step(
            &mut as_state(&mut tables, c),
            &row_ids,
            &grads,
            &vec![1e-3; c],
            &CONFIG,
            None,
        )
        .unwrap();
        let expected: Vec<f32> = (0..c)
            .map(|j| {
                let column = grads.iter().skip(j).step_by(c);
                column.fold(0.0f32, |a: f32, x: &f32| {
                    if x.is_finite() {
                        a.max(x.abs())
                    } else {
                        f32::INFINITY
                    }
                })
            })
            .collect();
        assert_eq!(report.peaks, expected);
        assert_eq!(report.rejected_rows, 3);
        let huge = [f32::INFINITY, f32::INFINITY, 3e20, f32::MAX, f32::INFINITY];
        assert_eq!(report.peaks, huge);
    }

    /// Each way a finite gradient's update can come out NaN or infinite — a stored moment
    /// or parameter already so, in any channel — is counted once per row, and rows of
    /// huge but finite values are not.
    #[test]
    fn every_non_finite_update_is_counted_and_no_finite_one() {
        let c = 3;
        let stored = [
            (1, "m", f32::INFINITY),
            (2, "m", f32::NAN),
            (0, "v", f32::INFINITY),
            (2, "v", -f32::NAN),
            (1, "p", f32::NEG_INFINITY),
            (0, "p", f32::NAN),
        ];
        for (ch, table, value) in stored {
            for finite_neighbour in [f32::MAX, -f32::MAX, 1e38] {
                let mut tables = state(2, c);
                let (p, m, v, _) = &mut tables;
                // Row 0 is finite but at the edge of the range; row 1 holds the special.
                p[..c].fill(finite_neighbour);
                m[..c].fill(finite_neighbour);
                v[..c].fill(f32::MAX);
                match table {
                    "m" => m[c + ch] = value,
                    "v" => v[c + ch] = value,
                    _ => p[c + ch] = value,
                }
                let mut st = as_state(&mut tables, c);
                let grads = [0.5; 6];
                let report = sparse_adam_step(&mut st, &[0, 1], &grads, &[1e-3; 3], &CONFIG, None).unwrap();
                assert_eq!(
                    (report.non_finite_rows, report.rejected_rows),
                    (1, 0),
                    "stored {table}[{ch}] = {value} beside {finite_neighbour}"
                );
            }
        }
    }

    #[test]
    fn a_journal_of_another_table_is_refused() {
        let (mut p, mut m, mut v, mut s) = state(4, 2);
        let mut st = SparseAdamState {
            param: &mut p,
            exp_avg: &mut m,
            exp_avg_sq: &mut v,
            steps: &mut s,
            channels: 2,
        };
        let mut journal = RowJournal::new(5, 2);
        let err = sparse_adam_step(
            &mut st,
            &[1],
            &[1.0, 1.0],
            &[0.1, 0.1],
            &CONFIG,
            Some(&mut journal),
        )
        .unwrap_err();
        assert!(matches!(err, Error::Shape { arg: "journal", .. }));
    }
}
