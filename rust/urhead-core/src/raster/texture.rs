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

use super::sparse::{
    sparse_texel_gradient, texel_entries, SparseTexels, TexelEntries, TextureSamples, MAX_SAMPLE_CHUNKS,
};
use super::taps::{
    bilinear_taps, gradient_taps, prefetch_taps, uv_gradient, uv_gradient_ahead, Taps, TexShape,
    PREFETCH_DISTANCE, SAMPLE_CHUNK,
};
use crate::error::{check_finite, check_len, checked_size, Error, Result};
use crate::memory::{assume_written, unwritten, write_zeros, written_part, zeroed, Slot};
use crate::Real;

/// Texel indices are stored as u32.
const MAX_TEXELS: usize = u32::MAX as usize;

/// `o = Σ_k w_k·rows_k`, one channel at a time: a plain loop over zipped slices, which
/// the loop vectoriser turns into full vectors (it checks at run time that `o` does not
/// overlap the rows). Blocks of 8 indexed channels stayed scalar (bounds checks and
/// stores between the loads defeat the block vectoriser), ~30 % of a lookup's time.
#[inline(always)]
pub(crate) fn blend<T: Real, O: Slot<T>>(o: &mut [O], rows: [&[T]; 4], w: [T; 4]) {
    let [r0, r1, r2, r3] = rows.map(|r| &r[..o.len()]); // every row covers the output
    let values = o.iter_mut().zip(r0).zip(r1).zip(r2).zip(r3);
    for ((((o, &a), &b), &c), &d) in values {
        o.set(w[0] * a + w[1] * b + w[2] * c + w[3] * d);
    }
}

pub(crate) fn validate<T: Real, S>(tex: &[S], shape: &TexShape, uv: &[T]) -> Result<usize> {
    let n = validate_layout(shape, uv)?;
    check_len(
        "tex",
        tex,
        shape.height * shape.width * shape.channels,
        &format!("({}, {}, {})", shape.height, shape.width, shape.channels),
    )?;
    Ok(n)
}

/// The texture's sides and the UV array's length; returns the number of samples `N`.
fn validate_layout<T: Real>(shape: &TexShape, uv: &[T]) -> Result<usize> {
    if shape.height == 0 || shape.width == 0 || shape.channels == 0 {
        return Err(Error::Shape {
            arg: "tex",
            expected: "(Ht, Wt, C) with every side ≥ 1".into(),
            got: format!("({}, {}, {})", shape.height, shape.width, shape.channels),
        });
    }
    checked_size("tex texels", &[shape.height, shape.width], MAX_TEXELS)?;
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
    let mut out = unwritten("texture samples (N, C)", n * c)?;
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
                match &taps[i] {
                    Some(t) => blend(
                        o,
                        t.texel.map(|k| &tex[k as usize * c..(k as usize + 1) * c]),
                        t.weight,
                    ),
                    None => write_zeros(o),
                }
            }
            // SAFETY: every row of the chunk was written just above, blended or zeros.
            let out = unsafe { written_part(out) };
            // x·0 ≠ 0 exactly for NaN and ±inf; an OR-reduction vectorises (a float sum or
            // an early-exit `any` would not).
            out.iter()
                .fold(false, |bad, &x| bad | (x * T::zero() != T::zero()))
        })
        .reduce(|| false, |a, b| a | b);
    if non_finite {
        check_finite("tex", tex)?;
    }
    // SAFETY: the chunks partition `out`, and each wrote every one of its rows.
    Ok(unsafe { assume_written(out) })
}

/// The texture gradient of lookups of a `(Ht, Wt, C)` texture, given as `segments` (each
/// `uv (N_i, 2)`, `v_out (N_i, C)`), as its unsummed entries ([`TexelEntries`]): the same
/// texels and sums [`texture_backward`] lists for the segments' concatenation, for a
/// consumer that sums each texel's row as it uses it.
pub fn texture_gradient_entries<'a, T: Real>(
    height: usize,
    width: usize,
    channels: usize,
    segments: &[TextureSamples<'a, T>],
) -> Result<TexelEntries<'a, T>> {
    let shape = TexShape {
        height,
        width,
        channels,
    };
    validate_layout::<T>(&shape, &[])?; // the texture's sides
    let mut chunks = 0;
    for (i, segment) in segments.iter().enumerate() {
        let n = segment.uv.len() / 2;
        if segment.uv.len() % 2 != 0 || segment.v_out.len() != n * channels {
            return Err(Error::Shape {
                arg: "segments",
                expected: format!("uv (N, 2) and v_out (N, {channels}) in each segment"),
                got: format!(
                    "{} uv and {} v_out elements in segment {i}",
                    segment.uv.len(),
                    segment.v_out.len()
                ),
            });
        }
        chunks += n.div_ceil(SAMPLE_CHUNK);
    }
    check_sample_chunks(chunks)?;
    texel_entries(&shape, &[], segments, None) // the texture is read for v_uv only
}

/// The texture gradient's entries number samples in u32, chunk by chunk (a segment's
/// last chunk may be short).
fn check_sample_chunks(chunks: usize) -> Result<()> {
    if chunks > MAX_SAMPLE_CHUNKS {
        return Err(Error::TooLarge {
            what: "texture samples, numbered in u32 by chunks within a segment",
            requested: (chunks * SAMPLE_CHUNK) as u128,
            limit: (MAX_SAMPLE_CHUNKS * SAMPLE_CHUNK) as u128,
        });
    }
    Ok(())
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
        check_sample_chunks(n.div_ceil(SAMPLE_CHUNK))?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;

    /// Each row is the plain bilinear sum of the four texels around its UV (edges
    /// clamped), and a non-finite UV reads a row of zeros: every row written, in every
    /// chunk (the unit tests' unwritten buffers start as NaN).
    #[test]
    fn lookups_are_the_plain_bilinear_sums_and_zeros_off_the_texture() {
        let (h, w, c) = (5, 7, 3);
        let mut rng = Rng::new(3);
        let tex: Vec<f64> = rng.vec(h * w * c, -1.0, 1.0);
        let n = 2 * SAMPLE_CHUNK + 5;
        let mut uv: Vec<f64> = rng.vec(2 * n, -0.1, 1.1);
        let off = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY];
        for (k, bad) in off.into_iter().enumerate() {
            uv[2 * (k * SAMPLE_CHUNK + 1) + k % 2] = bad;
        }
        let out = texture_forward(&tex, h, w, c, &uv).unwrap();
        let texel = |row: f64, col: f64| {
            let (r, cl) = (row.clamp(0.0, (h - 1) as f64), col.clamp(0.0, (w - 1) as f64));
            &tex[(r as usize * w + cl as usize) * c..][..c]
        };
        for (s, got) in out.chunks_exact(c).enumerate() {
            let (u, v) = (uv[2 * s], uv[2 * s + 1]);
            if !(u.is_finite() && v.is_finite()) {
                assert!(got.iter().all(|&x| x == 0.0), "sample {s}: {got:?}");
                continue;
            }
            let (x, y) = (u * w as f64 - 0.5, (1.0 - v) * h as f64 - 0.5);
            let (x0, y0) = (x.floor(), y.floor());
            let (fx, fy) = (x - x0, y - y0);
            for ch in 0..c {
                let want = (1.0 - fx) * (1.0 - fy) * texel(y0, x0)[ch]
                    + fx * (1.0 - fy) * texel(y0, x0 + 1.0)[ch]
                    + (1.0 - fx) * fy * texel(y0 + 1.0, x0)[ch]
                    + fx * fy * texel(y0 + 1.0, x0 + 1.0)[ch];
                assert!(
                    (got[ch] - want).abs() < 1e-12,
                    "sample {s} channel {ch}: {} vs {want}",
                    got[ch]
                );
            }
        }
    }
}
