//! `texture`: bilinear texture lookup and its adjoint.
//!
//! Convention (OBJ): `u` runs left → right, `v` bottom → top; texel row 0 is the top of
//! the image (`v = 1`). Texel `(r, c)` of a `(Ht, Wt)` texture has its centre at
//! `u = (c + 0.5)/Wt`, `v = 1 − (r + 0.5)/Ht`. Addressing is clamp-to-edge: outside the
//! texel centres the nearest edge texels are used (the natural choice for UV atlases, where
//! wrapping would bleed one island into another), and the UV gradient is zero there.
//! A sample with a non-finite coordinate (NaN or ±inf) returns zeros and passes no
//! gradient. The texture gradient is a coalesced sparse list of the texels that received
//! gradient (see [`super::sparse`]).

use rayon::prelude::*;

use super::sparse::{sparse_texel_gradient, SparseTexels};
use crate::error::{check_finite, check_len, checked_size, Error, Result};
use crate::memory::{prefetch, zeroed};
use crate::Real;

/// Samples per parallel work item.
pub(crate) const SAMPLE_CHUNK: usize = 2048;
/// How many samples ahead texel rows are prefetched.
pub(crate) const PREFETCH_DISTANCE: usize = 8;
/// Texel indices are stored as u32.
const MAX_TEXELS: usize = u32::MAX as usize;

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
    fx: T,
    fy: T,
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

/// `o = Σ_k w_k·rows_k`, in blocks of 8 channels so the compiler emits full vectors.
#[inline(always)]
fn blend<T: Real>(o: &mut [T], rows: [&[T]; 4], w: [T; 4]) {
    let c = o.len();
    let rows = rows.map(|r| &r[..c]);
    let full = c / 8 * 8;
    for k0 in (0..full).step_by(8) {
        let mut acc = [T::zero(); 8];
        for j in 0..8 {
            let k = k0 + j;
            acc[j] = w[0] * rows[0][k] + w[1] * rows[1][k] + w[2] * rows[2][k] + w[3] * rows[3][k];
        }
        o[k0..k0 + 8].copy_from_slice(&acc);
    }
    for k in full..c {
        o[k] = w[0] * rows[0][k] + w[1] * rows[1][k] + w[2] * rows[2][k] + w[3] * rows[3][k];
    }
}

/// Starts loading a sample's texel rows: the two taps of a row are adjacent in memory.
#[inline(always)]
pub(crate) fn prefetch_taps<T: Real>(t: &Taps<T>, tex: &[T], c: usize) {
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

pub(crate) fn validate<T: Real>(tex: &[T], shape: &TexShape, uv: &[T]) -> Result<usize> {
    if shape.height == 0 || shape.width == 0 || shape.channels == 0 {
        return Err(Error::Shape {
            arg: "tex",
            expected: "(Ht, Wt, C) with every side ≥ 1".into(),
            got: format!("({}, {}, {})", shape.height, shape.width, shape.channels),
        });
    }
    checked_size("tex texels", &[shape.height, shape.width], MAX_TEXELS)?;
    check_len(
        "tex",
        tex,
        shape.height * shape.width * shape.channels,
        &format!("({}, {}, {})", shape.height, shape.width, shape.channels),
    )?;
    if uv.len() % 2 != 0 {
        return Err(Error::Shape {
            arg: "uv",
            expected: "(..., 2)".into(),
            got: format!("{} elements", uv.len()),
        });
    }
    Ok(uv.len() / 2)
}

/// Samples `tex (Ht, Wt, C)` at `uv (N, 2)` → `(N, C)`.
///
/// Texels are checked for finiteness lazily: only if a sampled value comes out non-finite
/// is the texture scanned, and the error names the first non-finite texel (a 2048² × 56
/// map is never scanned on the happy path).
pub fn texture_forward<T: Real>(
    tex: &[T],
    height: usize,
    width: usize,
    channels: usize,
    uv: &[T],
) -> Result<Vec<T>> {
    let shape = TexShape {
        height,
        width,
        channels,
    };
    let n = validate(tex, &shape, uv)?;
    let c = channels;
    let mut out = zeroed("texture samples (N, C)", n * c)?;
    let non_finite = out
        .par_chunks_mut(SAMPLE_CHUNK * c)
        .enumerate()
        .map(|(chunk, out)| {
            let first = chunk * SAMPLE_CHUNK;
            let uv = &uv[2 * first..2 * (first + out.len() / c)];
            let taps: Vec<Option<Taps<T>>> = uv
                .chunks_exact(2)
                .map(|p| bilinear_taps(p[0], p[1], &shape))
                .collect();
            for (i, o) in out.chunks_exact_mut(c).enumerate() {
                if let Some(Some(ahead)) = taps.get(i + PREFETCH_DISTANCE) {
                    prefetch_taps(ahead, tex, c);
                }
                if let Some(t) = &taps[i] {
                    blend(
                        o,
                        t.texel.map(|k| &tex[k as usize * c..(k as usize + 1) * c]),
                        t.weight,
                    );
                }
            }
            // x·0 ≠ 0 exactly for NaN and ±inf; an OR-reduction vectorises (a float sum or
            // an early-exit `any` would not).
            out.iter()
                .fold(false, |bad, &x| bad | (x * T::zero() != T::zero()))
        })
        .reduce(|| false, |a, b| a | b);
    if non_finite {
        check_finite("tex", tex)?;
    }
    Ok(out)
}

/// Gradients of [`texture_backward`]; a field is `Some` exactly when it was asked for.
#[derive(Debug, Clone, Default)]
pub struct TextureGrads<T> {
    /// Coalesced sparse gradient of the texture.
    pub v_tex: Option<SparseTexels<T>>,
    /// `(N, 2)`
    pub v_uv: Option<Vec<T>>,
}

/// Adjoint of [`texture_forward`] given `v_out (N, C)`.
pub fn texture_backward<T: Real>(
    tex: &[T],
    height: usize,
    width: usize,
    channels: usize,
    uv: &[T],
    v_out: &[T],
    need_tex: bool,
    need_uv: bool,
) -> Result<TextureGrads<T>> {
    let shape = TexShape {
        height,
        width,
        channels,
    };
    let n = validate(tex, &shape, uv)?;
    let c = channels;
    check_len("v_out", v_out, n * c, &format!("(N, C) = ({n}, {c})"))?;
    let mut v_uv = need_uv.then(|| zeroed("uv gradient (N, 2)", 2 * n)).transpose()?;
    let v_tex = if need_tex {
        Some(sparse_texel_gradient(
            &shape,
            tex,
            uv,
            v_out,
            v_uv.as_deref_mut(),
        )?)
    } else {
        if let Some(v_uv) = v_uv.as_deref_mut() {
            v_uv.par_chunks_mut(2 * SAMPLE_CHUNK)
                .enumerate()
                .for_each(|(chunk, v_uv)| {
                    let first = chunk * SAMPLE_CHUNK;
                    let taps = gradient_taps(&shape, uv, v_out, first, first + v_uv.len() / 2);
                    for (i, t) in taps.iter().enumerate() {
                        if let Some(t) = t {
                            uv_gradient_ahead(&taps, i, tex, c);
                            let g = &v_out[(first + i) * c..(first + i + 1) * c];
                            v_uv[2 * i..2 * i + 2].copy_from_slice(&uv_gradient(t, tex, g, &shape));
                        }
                    }
                });
        }
        None
    };
    Ok(TextureGrads { v_tex, v_uv })
}
