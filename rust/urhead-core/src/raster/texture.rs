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
use crate::Real;

/// Samples per parallel work item.
pub(crate) const SAMPLE_CHUNK: usize = 2048;
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
    let mut out = vec![T::zero(); n * c];
    let non_finite = out
        .par_chunks_mut(SAMPLE_CHUNK * c)
        .enumerate()
        .map(|(chunk, out)| {
            let mut bad = false;
            for (i, o) in out.chunks_exact_mut(c).enumerate() {
                let s = chunk * SAMPLE_CHUNK + i;
                let Some(t) = bilinear_taps(uv[2 * s], uv[2 * s + 1], &shape) else {
                    continue;
                };
                let rows = t.texel.map(|k| &tex[k as usize * c..(k as usize + 1) * c]);
                let [w0, w1, w2, w3] = t.weight;
                for k in 0..c {
                    o[k] = w0 * rows[0][k] + w1 * rows[1][k] + w2 * rows[2][k] + w3 * rows[3][k];
                }
                bad |= o.iter().any(|x| !x.is_finite());
            }
            bad
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
    let v_tex = need_tex.then(|| sparse_texel_gradient(&shape, uv, v_out));
    let v_uv = need_uv.then(|| {
        let mut v_uv = vec![T::zero(); 2 * n];
        v_uv.par_chunks_mut(2 * SAMPLE_CHUNK)
            .enumerate()
            .for_each(|(chunk, v_uv)| {
                for (i, d) in v_uv.chunks_exact_mut(2).enumerate() {
                    let s = chunk * SAMPLE_CHUNK + i;
                    let g = &v_out[s * c..(s + 1) * c];
                    let Some(t) = bilinear_taps(uv[2 * s], uv[2 * s + 1], &shape) else {
                        continue;
                    };
                    let rows = t.texel.map(|k| &tex[k as usize * c..(k as usize + 1) * c]);
                    let (gx, gy) = (T::one() - t.fx, T::one() - t.fy);
                    let (mut d_fx, mut d_fy) = (T::zero(), T::zero());
                    for k in 0..c {
                        d_fx += g[k] * (gy * (rows[1][k] - rows[0][k]) + t.fy * (rows[3][k] - rows[2][k]));
                        d_fy += g[k] * (gx * (rows[2][k] - rows[0][k]) + t.fx * (rows[3][k] - rows[1][k]));
                    }
                    // x = u·Wt − 0.5 and y = (1 − v)·Ht − 0.5.
                    d[0] = d_fx * T::c(width as f64);
                    d[1] = -d_fy * T::c(height as f64);
                }
            });
        v_uv
    });
    Ok(TextureGrads { v_tex, v_uv })
}
