//! The texture gradient as a coalesced sparse COO list, built without touching (or
//! allocating) the dense texture.
//!
//! Contract — the same as `torch.nn.Embedding(sparse=True)`, so `torch.optim.SparseAdam`
//! and a sparse Rust optimiser can consume it directly: `indices (2, K)` int64 rows then
//! columns, sorted by `(row, col)` and unique; `values (K, C)`. A texel is listed when at
//! least one sample with a finite UV and a non-zero output gradient gives it a non-zero
//! bilinear weight ("received gradient"); its value may still sum to zero.
//!
//! Samples may come in segments (several lookups' arrays, never joined): they are taken as
//! the concatenation of the segments in order, so the result is bit for bit the one of
//! the concatenated arrays.
//!
//! Deterministic for any thread count: samples are cut into fixed chunks (within a
//! segment), each emits `(texel, sample, weight)` entries in sample order, the entries are
//! partitioned into fixed texel-row buckets (chunk order preserved), each bucket is
//! radix-sorted by texel with a stable sort, and each texel's value is summed over its
//! entries in sample order.

use rayon::prelude::*;

use super::taps::{gradient_taps, uv_gradient, uv_gradient_ahead, TexShape, PREFETCH_DISTANCE, SAMPLE_CHUNK};
use crate::error::Result;
use crate::memory::{concatenated, prefetch, zeroed};
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

/// One texture lookup's samples: `uv (N, 2)` and their output gradient `v_out (N, C)`.
#[derive(Debug, Clone, Copy)]
pub struct TextureSamples<'a, T> {
    pub uv: &'a [T],
    pub v_out: &'a [T],
}

/// Sample chunks a gradient can number: a sample is `chunk · SAMPLE_CHUNK + i` in a u32.
pub(crate) const MAX_SAMPLE_CHUNKS: usize = (u32::MAX as usize + 1) / SAMPLE_CHUNK;

/// The sample chunks of `segments` in order, none spanning two segments (so a sample is
/// found by its chunk without searching the segments); `channels` is `C`.
fn sample_chunks<'a, T>(segments: &[TextureSamples<'a, T>], channels: usize) -> Vec<TextureSamples<'a, T>> {
    segments
        .iter()
        .flat_map(|s| {
            let uv = s.uv.chunks(2 * SAMPLE_CHUNK);
            uv.zip(s.v_out.chunks(channels * SAMPLE_CHUNK))
                .map(|(uv, v_out)| TextureSamples { uv, v_out })
        })
        .collect()
}

#[derive(Debug, Clone, Copy)]
struct Entry<T> {
    texel: u32,
    /// `chunk · SAMPLE_CHUNK + i`: in the order of the concatenated samples.
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
/// Borrows the output gradients it sums.
#[derive(Debug, Clone)]
pub struct TexelEntries<'a, T> {
    entries: Vec<Entry<T>>,
    /// `(K + 1,)` where each distinct texel's run starts in `entries`, then the end.
    starts: Vec<usize>,
    /// Each sample chunk's output gradients `(≤ SAMPLE_CHUNK, C)`, in sample order.
    chunk_rows: Vec<&'a [T]>,
    /// The texture's `Ht · Wt` and `C`.
    texel_count: usize,
    channels: usize,
}

impl<T: Real> TexelEntries<'_, T> {
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

    /// The output gradient `(C,)` of `sample`. Unchecked: the chunk lookup's two bounds
    /// checks made summing 403k texels of a 2048² map (one thread) 15.7 ms against 14.1 from
    /// one flat array; unchecked it is 13.6.
    #[inline(always)]
    fn v_out(&self, sample: u32) -> &[T] {
        let (chunk, i) = (sample as usize / SAMPLE_CHUNK, sample as usize % SAMPLE_CHUNK);
        let c = self.channels;
        // SAFETY: entries are made only by `texel_entries`, for sample `i` of chunk `chunk`
        // (numbered without overflow: it asserts the chunk count) after reading the chunk's
        // row `v_out[i·C..(i + 1)·C]` (checked, in `gradient_taps`), and `chunk_rows[chunk]`
        // is that chunk's `v_out`; neither changes after.
        unsafe {
            self.chunk_rows
                .get_unchecked(chunk)
                .get_unchecked(i * c..(i + 1) * c)
        }
    }

    /// Texel `k`'s gradient `(C,)` into `dst`: its entries' `weight · v_out[sample]`
    /// summed in sample order, the first written, not added (so `dst` is never read).
    #[inline(always)]
    pub fn sum_into(&self, k: usize, dst: &mut [T]) {
        let run = &self.entries[self.starts[k]..self.starts[k + 1]];
        for (d, g) in dst.iter_mut().zip(self.v_out(run[0].sample)) {
            *d = run[0].weight * *g;
        }
        for e in &run[1..] {
            for (d, g) in dst.iter_mut().zip(self.v_out(e.sample)) {
                *d += e.weight * *g;
            }
        }
    }

    /// Starts loading the output-gradient rows texel `k` sums (its first two entries).
    #[inline(always)]
    pub fn prefetch(&self, k: usize) {
        if let Some(&start) = self.starts.get(k) {
            for e in self.entries[start..].iter().take(2) {
                prefetch(self.v_out(e.sample));
            }
        }
    }
}

/// The entries of the texel gradient of the samples `segments` hold (each `uv (N_i, 2)`,
/// `v_out (N_i, C)`); fills `v_uv (Σ N_i, 2)` in the same pass over the samples when given
/// (it reads the same texels and output gradients). The segments must have been checked
/// against `shape`, and have at most [`MAX_SAMPLE_CHUNKS`] chunks.
pub(crate) fn texel_entries<'a, T: Real>(
    shape: &TexShape,
    tex: &[T],
    segments: &[TextureSamples<'a, T>],
    v_uv: Option<&mut [T]>,
) -> Result<TexelEntries<'a, T>> {
    let c = shape.channels;
    let buckets = Buckets::new(shape);
    let sample_chunks = sample_chunks(segments, c);
    assert!(
        sample_chunks.len() <= MAX_SAMPLE_CHUNKS,
        "callers check the sample count"
    );
    let mut v_uv_chunks = Vec::with_capacity(sample_chunks.len());
    let mut v_uv_rest = v_uv;
    for chunk in &sample_chunks {
        let (head, tail) = match v_uv_rest {
            Some(rest) => {
                let (head, tail) = rest.split_at_mut(chunk.uv.len());
                (Some(head), Some(tail))
            }
            None => (None, None),
        };
        v_uv_chunks.push(head);
        v_uv_rest = tail;
    }

    // 1. Entries per sample chunk, partitioned by bucket (stable counting sort).
    let chunks: Vec<(Vec<Entry<T>>, Vec<usize>)> = sample_chunks
        .par_iter()
        .zip(v_uv_chunks.par_iter_mut())
        .enumerate()
        .map(|(chunk, (samples, v_uv))| {
            let (uv, v_out) = (samples.uv, samples.v_out);
            let first = chunk * SAMPLE_CHUNK;
            let mut entries = Vec::with_capacity(2 * uv.len());
            let taps = gradient_taps(shape, uv, v_out, 0, uv.len() / 2);
            for (i, t) in taps.iter().enumerate() {
                let Some(t) = t else {
                    continue;
                };
                if let Some(v_uv) = v_uv.as_deref_mut() {
                    uv_gradient_ahead(&taps, i, tex, c);
                    let g = &v_out[i * c..(i + 1) * c];
                    v_uv[2 * i..2 * i + 2].copy_from_slice(&uv_gradient(t, tex, g, shape));
                }
                for k in 0..4 {
                    if t.weight[k] != T::zero() {
                        entries.push(Entry {
                            texel: t.texel[k],
                            sample: (first + i) as u32,
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
    // Where each distinct texel's run starts, per bucket in parallel: a bucket's first
    // entry always starts one (buckets hold disjoint texel ranges).
    let mut first = 0;
    let bucket_starts: Vec<usize> = sorted
        .iter()
        .map(|b| {
            first += b.len();
            first - b.len()
        })
        .collect();
    let starts: Vec<Vec<usize>> = sorted
        .par_iter()
        .zip(&bucket_starts)
        .map(|(bucket, &first)| {
            let mut starts = Vec::with_capacity(bucket.len());
            for (i, e) in bucket.iter().enumerate() {
                if i == 0 || bucket[i - 1].texel != e.texel {
                    starts.push(first + i);
                }
            }
            starts
        })
        .collect();
    let entries = concatenated("texel entries", &sorted)?;
    let mut starts = concatenated("texel entry starts", &starts)?;
    starts.push(entries.len());
    Ok(TexelEntries {
        entries,
        starts,
        chunk_rows: sample_chunks.iter().map(|chunk| chunk.v_out).collect(),
        texel_count: shape.height * shape.width,
        channels: c,
    })
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
    let texels = texel_entries(shape, tex, &[TextureSamples { uv, v_out }], v_uv)?;
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
                texels.prefetch(k + PREFETCH_DISTANCE);
                let texel = texels.texel(k);
                *r = (texel / shape.width) as i64;
                *cl = (texel % shape.width) as i64;
                texels.sum_into(k, dst);
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
