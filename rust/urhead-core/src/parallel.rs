//! Deterministic data parallelism: work is cut into fixed-size chunks whose boundaries do
//! not depend on the thread count, and per-chunk partial sums are merged in chunk order.

/// Splits a batch-major buffer `(B, N, row)` into per-chunk views: `views[c][b]` is the
/// slice of batch `b` covering rows `c·chunk_rows .. min((c+1)·chunk_rows, N)`.
pub fn batch_chunks_mut<T>(buf: &mut [T], batch: usize, row: usize, chunk_rows: usize) -> Vec<Vec<&mut [T]>> {
    let per_batch = buf.len() / batch.max(1);
    let num_chunks = (per_batch / row).div_ceil(chunk_rows);
    let mut views: Vec<Vec<&mut [T]>> = (0..num_chunks).map(|_| Vec::with_capacity(batch)).collect();
    if per_batch == 0 {
        return views;
    }
    for batch_slice in buf.chunks_mut(per_batch) {
        for (c, chunk) in batch_slice.chunks_mut(chunk_rows * row).enumerate() {
            views[c].push(chunk);
        }
    }
    views
}

/// `buf` in chunks of `size` for a parallel pass that writes an optional output, or
/// `tasks` Nones when there is no output: zipped with the pass's other chunks, the output
/// is written where asked for and skipped elsewhere, in the same single pass.
pub fn optional_chunks<T>(buf: Option<&mut [T]>, size: usize, tasks: usize) -> Vec<Option<&mut [T]>> {
    match buf {
        Some(buf) => buf.chunks_mut(size).map(Some).collect(),
        None => (0..tasks).map(|_| None).collect(),
    }
}

/// Sums equally long partial vectors in their given order (deterministic reduction).
pub fn sum_in_order<T: crate::Real>(partials: &[Vec<T>], len: usize) -> Vec<T> {
    let mut total = vec![T::zero(); len];
    for p in partials {
        for (t, x) in total.iter_mut().zip(p) {
            *t += *x;
        }
    }
    total
}

/// Dot product with 16 independent accumulators so LLVM vectorises it; the summation
/// order is fixed, so results are reproducible.
#[inline]
pub fn dot<T: crate::Real>(a: &[T], b: &[T]) -> T {
    let mut acc = [T::zero(); 16];
    let (ca, cb) = (a.chunks_exact(16), b.chunks_exact(16));
    let tail: T = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| *x * *y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for i in 0..16 {
            acc[i] += x[i] * y[i];
        }
    }
    for w in [8, 4, 2, 1] {
        for i in 0..w {
            let upper = acc[i + w];
            acc[i] += upper;
        }
    }
    acc[0] + tail
}

/// y += alpha·x
#[inline]
pub fn axpy<T: crate::Real>(alpha: T, x: &[T], y: &mut [T]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += alpha * *xi;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_cover_every_element_once() {
        let mut buf: Vec<u32> = (0..2 * 10 * 3).collect();
        let views = batch_chunks_mut(&mut buf, 2, 3, 4);
        assert_eq!(views.len(), 3);
        assert_eq!(views[2][1], &[54, 55, 56, 57, 58, 59]);
        let total: usize = views.iter().flatten().map(|v| v.len()).sum();
        assert_eq!(total, 60);
    }

    #[test]
    fn dot_matches_naive() {
        let a: Vec<f64> = (0..37).map(|i| i as f64 * 0.5).collect();
        let b: Vec<f64> = (0..37).map(|i| 1.0 - i as f64).collect();
        let naive: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert!((dot(&a, &b) - naive).abs() < 1e-9);
    }
}
