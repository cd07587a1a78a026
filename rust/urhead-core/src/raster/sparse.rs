//! The texture gradient as a coalesced sparse COO list, built without touching (or
//! allocating) the dense texture.
//!
//! Contract — the same as `torch.nn.Embedding(sparse=True)`, so `torch.optim.SparseAdam`
//! and a sparse Rust optimiser can consume it directly: `indices (2, K)` int64 rows then
//! columns, sorted by `(row, col)` and unique; `values (K, C)`. A texel is listed when at
//! least one sample with a finite UV and a non-zero output gradient gives it a non-zero
//! bilinear weight ("received gradient"); its value may still sum to zero.
//!
//! Deterministic for any thread count: samples are cut into fixed chunks, each emits
//! `(texel, sample, weight)` entries in sample order, the entries are partitioned into
//! fixed texel-row buckets (chunk order preserved), each bucket is radix-sorted by texel
//! with a stable sort, and each texel's value is summed over its entries in sample order.

use rayon::prelude::*;

use super::taps::{gradient_taps, uv_gradient, uv_gradient_ahead, TexShape, PREFETCH_DISTANCE, SAMPLE_CHUNK};
use crate::error::Result;
use crate::memory::{prefetch, zeroed};
use crate::parallel::optional_chunks;
use crate::Real;

/// Target number of texel buckets (fewer for small textures).
const NUM_BUCKETS: usize = 64;

/// A coalesced sparse texel gradient.
#[derive(Debug, Clone, PartialEq)]
pub struct SparseTexels<T> {
    /// `(2, K)`: texel rows, then texel columns; sorted by (row, col), unique.
    pub indices: Vec<i64>,
    /// `(K, C)`
    pub values: Vec<T>,
    pub nnz: usize,
}

#[derive(Debug, Clone, Copy)]
struct Entry<T> {
    texel: u32,
    sample: u32,
    weight: T,
}

/// Which texels form a bucket: consecutive rows, so buckets are in texel order.
struct Buckets {
    texels_per_bucket: usize,
    count: usize,
}

impl Buckets {
    fn new(shape: &TexShape) -> Self {
        let rows = shape.height.div_ceil(NUM_BUCKETS).max(1);
        let texels_per_bucket = rows * shape.width;
        Self {
            texels_per_bucket,
            count: (shape.height * shape.width).div_ceil(texels_per_bucket),
        }
    }

    #[inline(always)]
    fn of(&self, texel: u32) -> usize {
        texel as usize / self.texels_per_bucket
    }
}

/// The entries of a texel gradient before they are summed: every `(texel, sample,
/// weight)` a sample with a finite UV and a non-zero output gradient gives a non-zero
/// bilinear weight, sorted by texel (stable: samples in order within a texel), with the
/// run each distinct texel occupies. Summing a run gives that texel's gradient row, which
/// [`sparse_texel_gradient`] stores and a fused optimiser step
/// ([`crate::adam::sparse_adam_step_sampled`]) consumes as it goes, never storing it.
#[derive(Debug, Clone)]
pub struct TexelEntries<T> {
    entries: Vec<Entry<T>>,
    /// `(K + 1,)` where each distinct texel's run starts in `entries`, then the end.
    starts: Vec<usize>,
    /// The texture's `Ht · Wt` and `C`.
    texel_count: usize,
    channels: usize,
}

impl<T: Real> TexelEntries<T> {
    /// Distinct texels `K`.
    pub fn len(&self) -> usize {
        self.starts.len() - 1
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The texture's channels `C`.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The texture's texels `Ht · Wt`.
    pub fn texel_count(&self) -> usize {
        self.texel_count
    }

    /// The flat index (`row · Wt + column`) of the `k`-th distinct texel, increasing in `k`.
    #[inline(always)]
    pub fn texel(&self, k: usize) -> usize {
        self.entries[self.starts[k]].texel as usize
    }

    /// Texel `k`'s gradient `(C,)` into `dst`: its entries' `weight · v_out[sample]`
    /// summed in sample order, the first written, not added (so `dst` is never read).
    #[inline(always)]
    pub fn sum_into(&self, k: usize, v_out: &[T], dst: &mut [T]) {
        let c = self.channels;
        let run = &self.entries[self.starts[k]..self.starts[k + 1]];
        let row = |e: &Entry<T>| &v_out[e.sample as usize * c..(e.sample as usize + 1) * c];
        for (d, g) in dst.iter_mut().zip(row(&run[0])) {
            *d = run[0].weight * *g;
        }
        for e in &run[1..] {
            for (d, g) in dst.iter_mut().zip(row(e)) {
                *d += e.weight * *g;
            }
        }
    }

    /// Starts loading the output-gradient rows texel `k` sums (its first two entries).
    #[inline(always)]
    pub fn prefetch(&self, k: usize, v_out: &[T]) {
        let c = self.channels;
        if let Some(&start) = self.starts.get(k) {
            for e in self.entries[start..].iter().take(2) {
                prefetch(&v_out[e.sample as usize * c..(e.sample as usize + 1) * c]);
            }
        }
    }
}

/// The entries of the texel gradient of `v_out (N, C)` at `uv (N, 2)`; fills `v_uv (N, 2)`
/// in the same pass over the samples when given (it reads the same texels and output
/// gradients). `uv` and `v_out` must have been checked against `shape`.
pub(crate) fn texel_entries<T: Real>(
    shape: &TexShape,
    tex: &[T],
    uv: &[T],
    v_out: &[T],
    v_uv: Option<&mut [T]>,
) -> TexelEntries<T> {
    let c = shape.channels;
    let n = uv.len() / 2;
    let buckets = Buckets::new(shape);
    let num_chunks = n.div_ceil(SAMPLE_CHUNK);
    let mut v_uv_chunks = optional_chunks(v_uv, 2 * SAMPLE_CHUNK, num_chunks);

    // 1. Entries per sample chunk, partitioned by bucket (stable counting sort).
    let chunks: Vec<(Vec<Entry<T>>, Vec<usize>)> = v_uv_chunks
        .par_iter_mut()
        .enumerate()
        .map(|(chunk, v_uv)| {
            let first = chunk * SAMPLE_CHUNK;
            let last = (first + SAMPLE_CHUNK).min(n);
            let mut entries = Vec::with_capacity(4 * (last - first));
            let taps = gradient_taps(shape, uv, v_out, first, last);
            for (i, t) in taps.iter().enumerate() {
                let Some(t) = t else {
                    continue;
                };
                let s = first + i;
                if let Some(v_uv) = v_uv.as_deref_mut() {
                    uv_gradient_ahead(&taps, i, tex, c);
                    let g = &v_out[s * c..(s + 1) * c];
                    v_uv[2 * i..2 * i + 2].copy_from_slice(&uv_gradient(t, tex, g, shape));
                }
                for k in 0..4 {
                    if t.weight[k] != T::zero() {
                        entries.push(Entry {
                            texel: t.texel[k],
                            sample: s as u32,
                            weight: t.weight[k],
                        });
                    }
                }
            }
            partition(entries, &buckets)
        })
        .collect();

    // 2. Per bucket: gather in chunk order, sort by texel (stable); buckets are in texel
    // order, so their concatenation is sorted.
    let sorted: Vec<Vec<Entry<T>>> = (0..buckets.count)
        .into_par_iter()
        .map(|b| {
            let mut entries = Vec::with_capacity(chunks.iter().map(|(_, o)| o[b + 1] - o[b]).sum());
            for (e, o) in &chunks {
                entries.extend_from_slice(&e[o[b]..o[b + 1]]);
            }
            radix_sort_by_texel(
                entries,
                (b * buckets.texels_per_bucket) as u32,
                buckets.texels_per_bucket,
            )
        })
        .collect();
    drop(chunks);
    let entries = sorted.concat();
    let mut starts: Vec<usize> = Vec::with_capacity(entries.len() / 2 + 1);
    for (i, e) in entries.iter().enumerate() {
        if i == 0 || entries[i - 1].texel != e.texel {
            starts.push(i);
        }
    }
    starts.push(entries.len());
    TexelEntries {
        entries,
        starts,
        texel_count: shape.height * shape.width,
        channels: c,
    }
}

/// The sparse texel gradient of `v_out (N, C)`; fills `v_uv (N, 2)` in the same pass over
/// the samples when given.
pub(crate) fn sparse_texel_gradient<T: Real>(
    shape: &TexShape,
    tex: &[T],
    uv: &[T],
    v_out: &[T],
    v_uv: Option<&mut [T]>,
) -> Result<SparseTexels<T>> {
    let c = shape.channels;
    let texels = texel_entries(shape, tex, uv, v_out, v_uv);
    let nnz = texels.len();

    // 3. Each texel's sum into disjoint slices of the output, in fixed blocks of texels.
    let mut indices: Vec<i64> = zeroed("texture gradient indices (2, nnz)", 2 * nnz)?;
    let mut values: Vec<T> = zeroed("texture gradient values (nnz, C)", nnz * c)?;
    let (rows, cols) = indices.split_at_mut(nnz);
    rows.par_chunks_mut(TEXEL_BLOCK)
        .zip(cols.par_chunks_mut(TEXEL_BLOCK))
        .zip(values.par_chunks_mut(TEXEL_BLOCK * c))
        .enumerate()
        .for_each(|(block, ((rows, cols), vals))| {
            let first = block * TEXEL_BLOCK;
            for (i, ((r, cl), dst)) in rows
                .iter_mut()
                .zip(cols)
                .zip(vals.chunks_exact_mut(c))
                .enumerate()
            {
                let k = first + i;
                texels.prefetch(k + PREFETCH_DISTANCE, v_out);
                let texel = texels.texel(k);
                *r = (texel / shape.width) as i64;
                *cl = (texel % shape.width) as i64;
                texels.sum_into(k, v_out, dst);
            }
        });
    Ok(SparseTexels { indices, values, nnz })
}

/// Texels per parallel work item when summing.
const TEXEL_BLOCK: usize = 1024;

/// Stable counting sort of entries by bucket; returns them with bucket offsets.
fn partition<T: Copy>(entries: Vec<Entry<T>>, buckets: &Buckets) -> (Vec<Entry<T>>, Vec<usize>) {
    let mut offsets = vec![0usize; buckets.count + 1];
    for e in &entries {
        offsets[buckets.of(e.texel) + 1] += 1;
    }
    for b in 0..buckets.count {
        offsets[b + 1] += offsets[b];
    }
    let mut fill = offsets.clone();
    let mut out = entries.clone(); // every slot is overwritten below
    for e in entries {
        let b = buckets.of(e.texel);
        out[fill[b]] = e;
        fill[b] += 1;
    }
    (out, offsets)
}

/// Stable LSD radix sort (8 bits a pass) by `texel − base`, which is below `span`.
fn radix_sort_by_texel<T: Copy>(mut entries: Vec<Entry<T>>, base: u32, span: usize) -> Vec<Entry<T>> {
    let bits = usize::BITS - (span.max(2) - 1).leading_zeros();
    let mut scratch = entries.clone();
    let mut shift = 0;
    while shift < bits {
        let mut offsets = [0usize; 257];
        for e in &entries {
            offsets[(((e.texel - base) >> shift) & 0xff) as usize + 1] += 1;
        }
        if offsets[1..].contains(&entries.len()) {
            shift += 8; // every key shares this digit: the pass would not move anything
            continue;
        }
        for d in 0..256 {
            offsets[d + 1] += offsets[d];
        }
        for e in &entries {
            let d = (((e.texel - base) >> shift) & 0xff) as usize;
            scratch[offsets[d]] = *e;
            offsets[d] += 1;
        }
        std::mem::swap(&mut entries, &mut scratch);
        shift += 8;
    }
    entries
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_sort_is_stable_and_sorted() {
        let entries: Vec<Entry<f32>> = (0..1000u32)
            .map(|i| Entry {
                texel: 500 + (i * 7919) % 300,
                sample: i,
                weight: 1.0,
            })
            .collect();
        let sorted = radix_sort_by_texel(entries, 500, 300);
        for w in sorted.windows(2) {
            assert!(w[0].texel < w[1].texel || (w[0].texel == w[1].texel && w[0].sample < w[1].sample));
        }
    }
}
