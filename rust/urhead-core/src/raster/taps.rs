//! Bilinear taps of texture samples, shared by the texture lookup ([`super::texture`]) and
//! its sparse texel gradient ([`super::sparse`]): where a sample reads, how its rows are
//! prefetched, and the UV gradient of one sample.
//!
//! Convention (OBJ): `u` runs left → right, `v` bottom → top; texel row 0 is the top of
//! the image (`v = 1`); clamp-to-edge addressing (see [`super::texture`]).

use crate::memory::prefetch;
use crate::Real;

/// Samples per parallel work item.
pub(crate) const SAMPLE_CHUNK: usize = 2048;
/// How many samples ahead texel rows are prefetched.
pub(crate) const PREFETCH_DISTANCE: usize = 8;
/// Texture shape `(Ht, Wt, C)`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TexShape {
    pub height: usize,
    pub width: usize,
    pub channels: usize,
}

/// The four bilinear taps of one sample, in the order `(r0, c0), (r0, c1), (r1, c0),
/// (r1, c1)`, with the fractional position needed by the UV gradient.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Taps<T> {
    pub texel: [u32; 4],
    pub weight: [T; 4],
    pub fx: T,
    pub fy: T,
}

/// The one function both passes use to place a sample. `None` for non-finite coordinates.
#[inline(always)]
pub(crate) fn bilinear_taps<T: Real>(u: T, v: T, shape: &TexShape) -> Option<Taps<T>> {
    if !(u.is_finite() && v.is_finite()) {
        return None;
    }
    let x = u * T::c(shape.width as f64) - T::c(0.5);
    let y = (T::one() - v) * T::c(shape.height as f64) - T::c(0.5);
    let (c0, c1, fx) = axis(x, shape.width);
    let (r0, r1, fy) = axis(y, shape.height);
    let (gx, gy) = (T::one() - fx, T::one() - fy);
    let w = shape.width;
    Some(Taps {
        texel: [r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1].map(|t| t as u32),
        weight: [gx * gy, fx * gy, gx * fy, fx * fy],
        fx,
        fy,
    })
}

/// Starts loading a sample's texel rows: the two taps of a row are adjacent in memory.
#[inline(always)]
pub(crate) fn prefetch_taps<T: Real, S>(t: &Taps<T>, tex: &[S], c: usize) {
    for pair in [[t.texel[0], t.texel[1]], [t.texel[2], t.texel[3]]] {
        let (lo, hi) = (pair[0].min(pair[1]) as usize, pair[0].max(pair[1]) as usize);
        prefetch(&tex[lo * c..(hi + 1) * c]);
    }
}

/// Continuous texel coordinate → the two clamped texel indices and the fraction. The
/// coordinate is first limited to [−1, n], where both taps are already the edge texel, so
/// huge or infinite-product coordinates cannot overflow the index.
#[inline(always)]
fn axis<T: Real>(x: T, n: usize) -> (usize, usize, T) {
    let x = x.max(-T::one()).min(T::c(n as f64));
    let floor = x.floor();
    let i0 = floor.to_i64().unwrap_or(0);
    let last = n as i64 - 1;
    (
        i0.clamp(0, last) as usize,
        (i0 + 1).clamp(0, last) as usize,
        x - floor,
    )
}

/// Gradient of one sample's `(u, v)` given its output gradient `g (C)`: the bilinear
/// derivative along x and y, times `dx/du = Wt` and `dy/dv = −Ht`. Clamped taps coincide,
/// so the gradient is zero outside the texel centres.
#[inline(always)]
pub(crate) fn uv_gradient<T: Real>(t: &Taps<T>, tex: &[T], g: &[T], shape: &TexShape) -> [T; 2] {
    let c = shape.channels;
    let rows = t.texel.map(|k| &tex[k as usize * c..(k as usize + 1) * c]);
    let g = &g[..c];
    let (gx, gy) = (T::one() - t.fx, T::one() - t.fy);
    // Eight independent partial sums per axis (a fixed order, so still deterministic) let
    // the channel loop vectorise.
    let (mut d_fx, mut d_fy) = ([T::zero(); 8], [T::zero(); 8]);
    for k in 0..c {
        let lane = k % 8;
        d_fx[lane] += g[k] * (gy * (rows[1][k] - rows[0][k]) + t.fy * (rows[3][k] - rows[2][k]));
        d_fy[lane] += g[k] * (gx * (rows[2][k] - rows[0][k]) + t.fx * (rows[3][k] - rows[1][k]));
    }
    let (d_fx, d_fy) = (sum8(d_fx), sum8(d_fy));
    [d_fx * T::c(shape.width as f64), -d_fy * T::c(shape.height as f64)]
}

/// Taps of samples `first..last` that received a non-zero output gradient (`None` for the
/// others and for non-finite coordinates): the samples both backward passes visit.
pub(crate) fn gradient_taps<T: Real>(
    shape: &TexShape,
    uv: &[T],
    v_out: &[T],
    first: usize,
    last: usize,
) -> Vec<Option<Taps<T>>> {
    let c = shape.channels;
    (first..last)
        .map(|s| {
            let zero = v_out[s * c..(s + 1) * c]
                .iter()
                .fold(true, |z, g| z & (*g == T::zero()));
            (!zero)
                .then(|| bilinear_taps(uv[2 * s], uv[2 * s + 1], shape))
                .flatten()
        })
        .collect()
}

/// Prefetches the texels of the sample [`PREFETCH_DISTANCE`] after `i`, if any.
#[inline(always)]
pub(crate) fn uv_gradient_ahead<T: Real>(taps: &[Option<Taps<T>>], i: usize, tex: &[T], c: usize) {
    if let Some(Some(ahead)) = taps.get(i + PREFETCH_DISTANCE) {
        prefetch_taps(ahead, tex, c);
    }
}

/// Pairwise sum of eight lanes, in a fixed order.
#[inline(always)]
fn sum8<T: Real>(a: [T; 8]) -> T {
    ((a[0] + a[4]) + (a[2] + a[6])) + ((a[1] + a[5]) + (a[3] + a[7]))
}
