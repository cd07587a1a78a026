//! `sh_texture`: a bilinear texture lookup shaded with spherical harmonics in one pass —
//! `rgb = max(Σ_k b_k(dir)·c_k(uv) + 0.5, 0)` from the texture's first `3·(degree+1)²`
//! channels (coefficient-major, 3DGS constants, [`crate::sh`]) plus a plain lookup of a
//! range of other channels (`extra`, e.g. the rest-pose normal) — and its adjoint.
//!
//! Why one op: the mesh branch looks a 56-channel map up at every covered pixel only to
//! turn 48 channels into a colour and keep 3 more. As a lookup followed by
//! [`crate::shading`], the backward's UV gradient reads the four texel rows of every pixel
//! a second time (a random read as large as the forward's). Here the forward, while the
//! rows are in cache, also keeps the derivatives of its few outputs along `u` and `v` (the
//! *slopes*, `(N, 2, 3 + E)`), so the backward never reads the texture: the UV gradient is
//! a dot product with the slopes, and the texture's gradient is returned as the
//! full-width per-sample rows `(N, C)` a lookup's backward would have received (for the
//! sparse texel gradient or a `TextureGather`).
//!
//! Exactness: the values are bit for bit those of [`texture_forward`](super::texture_forward)
//! followed by [`shade_forward`](crate::shading::shade_forward) (the same blend per
//! channel, the same order of the SH sum); the rows' gradient likewise bit for bit that of
//! [`shade_backward`](crate::shading::shade_backward) plus the extra channels' gradient. The
//! UV gradient equals [`texture_backward`](super::texture_backward)'s up to rounding (it is
//! summed over the outputs instead of over the channels).
//!
//! The texture may be stored as float16 ([`Texel`]) for a forward computing in f32: the
//! values are then those of the f32 texture the float16 one widens to, exactly.
//!
//! Texture conventions are the lookup's (OBJ UVs, clamp-to-edge; a sample with a
//! non-finite coordinate reads zeros — colour 0.5 — and passes no UV gradient). Directions
//! are constants and must be finite.

use std::ops::Range;

use rayon::prelude::*;

use super::taps::{bilinear_taps, prefetch_taps, Taps, TexShape, PREFETCH_DISTANCE, SAMPLE_CHUNK};
use super::texel::Texel;
use super::texture::{blend, validate};
use crate::error::{check_finite, check_len, Error, Result};
use crate::memory::{assume_written, copy_short, unwritten, write_zeros, written_part, zeroed};
use crate::parallel::optional_chunks;
use crate::sh::{direction, num_sh_coeffs, sh_basis, sh_sum, sh_sum_adjoint, unclamped};
use crate::Real;

/// What the forward reads (`S`: the texture's element type, `T` or float16).
#[derive(Debug, Clone)]
pub struct ShTextureInputs<'a, T, S = T> {
    /// `(Ht, Wt, C)` texture; channel `3k + c` is SH coefficient `k` of colour `c`.
    pub tex: &'a [S],
    pub height: usize,
    pub width: usize,
    pub channels: usize,
    /// `(N, 2)` texture coordinates.
    pub uv: &'a [T],
    /// `(N, 3)` unit view directions (constants).
    pub dirs: &'a [T],
    /// 0–3: the colour is the first `3·(degree+1)²` channels.
    pub degree: usize,
    /// Channels looked up as they are, after the colour; may be empty.
    pub extra: Range<usize>,
}

/// What the forward returns; the optional parts exactly when asked for.
#[derive(Debug, Clone)]
pub struct ShTextureOutput<T> {
    /// `(N, 3)` the colour.
    pub rgb: Vec<T>,
    /// `(N, E)` the extra channels. Apart from the colour, so that neither is a strided
    /// slice of one array: their gradients then arrive apart too, with no zero-filled
    /// `(N, 3 + E)` array per part and no sum of the two (autograd's slice backward).
    pub extra: Vec<T>,
    /// `(N, 3)` the colour before its clamp at 0 (which channels pass gradient).
    pub raw_rgb: Option<Vec<T>>,
    /// `(N, 2, 3 + E)` ∂values/∂u then ∂values/∂v (the colour's before the clamp).
    pub slopes: Option<Vec<T>>,
}

/// What the backward reads: the forward's saved outputs and the values' gradient.
#[derive(Debug, Clone)]
pub struct ShTextureGradInputs<'a, T> {
    /// `(N, 2)` the forward's coordinates (a non-finite one passes no UV gradient).
    pub uv: &'a [T],
    /// `(N, 3)` the forward's directions.
    pub dirs: &'a [T],
    pub degree: usize,
    /// The texture's channel count `C` (the rows' width).
    pub channels: usize,
    pub extra: Range<usize>,
    /// `(N, 3)` [`ShTextureOutput::raw_rgb`].
    pub raw_rgb: &'a [T],
    /// `(N, 2, 3 + E)` [`ShTextureOutput::slopes`]; without them no UV gradient.
    pub slopes: Option<&'a [T]>,
    /// `(N, 3)` ∂L/∂rgb; `None` for zero.
    pub v_rgb: Option<&'a [T]>,
    /// `(N, E)` ∂L/∂extra; `None` for zero.
    pub v_extra: Option<&'a [T]>,
}

/// The backward's gradients, `None` where not asked for.
#[derive(Debug, Clone)]
pub struct ShTextureGrads<T> {
    /// `(N, C)` each sample's gradient with respect to its interpolated texture row (zero
    /// outside the colour and the extra channels).
    pub v_rows: Option<Vec<T>>,
    /// `(N, 2)`
    pub v_uv: Option<Vec<T>>,
}

/// Checks the channel ranges of a texture of `channels` channels; returns the colour's
/// channel count `3·(degree+1)²`.
fn check_channels(degree: usize, channels: usize, extra: &Range<usize>) -> Result<usize> {
    if degree > 3 {
        return Err(Error::Invalid {
            arg: "degree",
            reason: format!("must be 0, 1, 2 or 3, got {degree}"),
        });
    }
    let colour = 3 * num_sh_coeffs(degree);
    if colour > channels {
        return Err(Error::Invalid {
            arg: "tex",
            reason: format!("{channels} channels cannot hold the {colour} coefficients of degree {degree}"),
        });
    }
    if extra.start > extra.end || extra.end > channels || (extra.start < colour && !extra.is_empty()) {
        return Err(Error::Invalid {
            arg: "extra",
            reason: format!(
                "must be a range of channels after the colour ({colour}..{channels}), got {}..{}",
                extra.start, extra.end
            ),
        });
    }
    Ok(colour)
}

/// The interpolated row's derivatives along the texel axes x and y (per unit texel).
#[inline(always)]
fn texel_slopes<T: Real>(d_fx: &mut [T], d_fy: &mut [T], rows: [&[T]; 4], t: &Taps<T>) {
    let (gx, gy) = (T::one() - t.fx, T::one() - t.fy);
    let n = d_fx.len();
    let rows = rows.map(|r| &r[..n]);
    for k in 0..n {
        d_fx[k] = gy * (rows[1][k] - rows[0][k]) + t.fy * (rows[3][k] - rows[2][k]);
        d_fy[k] = gx * (rows[2][k] - rows[0][k]) + t.fx * (rows[3][k] - rows[1][k]);
    }
}

/// Shades `tex` at `uv` along `dirs` ([module docs](self)). With `for_backward` the
/// pre-clamp colour is kept, with `slopes` the values' UV derivatives.
///
/// Texels are checked for finiteness lazily, as the lookup does: only if a value comes out
/// non-finite is the texture scanned, and the error names the first non-finite texel.
pub fn sh_texture_forward<T: Real, S: Texel<T>>(
    inputs: &ShTextureInputs<'_, T, S>,
    for_backward: bool,
    slopes: bool,
) -> Result<ShTextureOutput<T>> {
    let shape = TexShape {
        height: inputs.height,
        width: inputs.width,
        channels: inputs.channels,
    };
    let n = validate(inputs.tex, &shape, inputs.uv)?;
    let colour = check_channels(inputs.degree, inputs.channels, &inputs.extra)?;
    check_len("dirs", inputs.dirs, 3 * n, &format!("(N, 3) = ({n}, 3)"))?;
    check_finite("dirs", inputs.dirs)?;
    let (c, extra) = (inputs.channels, inputs.extra.clone());
    let (e, width) = (extra.len(), 3 + extra.len());
    // Every output is written whole, sample by sample, below: none is zeroed first.
    let mut rgb = unwritten("sh_texture colour (N, 3)", n * 3)?;
    let mut extra_out = unwritten("sh_texture extra channels (N, E)", n * e)?;
    let mut raw = for_backward
        .then(|| unwritten("sh_texture colour (N, 3)", n * 3))
        .transpose()?;
    let mut slope_out = slopes
        .then(|| unwritten("sh_texture slopes (N, 2, 3 + E)", n * 2 * width))
        .transpose()?;
    let tasks = n.div_ceil(SAMPLE_CHUNK);
    let extra_chunks = optional_chunks((e > 0).then_some(&mut extra_out[..]), SAMPLE_CHUNK * e, tasks);
    let raw_chunks = optional_chunks(raw.as_deref_mut(), SAMPLE_CHUNK * 3, tasks);
    let slope_chunks = optional_chunks(slope_out.as_deref_mut(), SAMPLE_CHUNK * 2 * width, tasks);
    // dx/du = Wt, dy/dv = −Ht (texel row 0 is the top).
    let (du, dv) = (T::c(inputs.width as f64), -T::c(inputs.height as f64));
    let non_finite = rgb
        .par_chunks_mut(SAMPLE_CHUNK * 3)
        .zip(extra_chunks)
        .zip(raw_chunks)
        .zip(slope_chunks)
        .enumerate()
        .map(|(chunk, (((rgb_out, mut extra_out), mut raw), mut slope_out))| {
            let first = chunk * SAMPLE_CHUNK;
            let count = rgb_out.len() / 3;
            let uv = &inputs.uv[2 * first..2 * (first + count)];
            let taps: Vec<Option<Taps<T>>> = uv
                .chunks_exact(2)
                .map(|p| bilinear_taps(p[0], p[1], &shape))
                .collect();
            // The sample's interpolated row and its texel-axis slopes (used channels only).
            let mut row = vec![T::zero(); c];
            let mut widened = vec![T::zero(); 4 * c]; // float16 rows as T
            let used = [&(0..colour), &extra];
            let (mut d_fx, mut d_fy) = (vec![T::zero(); c], vec![T::zero(); c]);
            for (i, out) in rgb_out.chunks_exact_mut(3).enumerate() {
                if let Some(Some(ahead)) = taps.get(i + PREFETCH_DISTANCE) {
                    prefetch_taps(ahead, inputs.tex, c);
                }
                match &taps[i] {
                    Some(t) if slope_out.is_none() => {
                        S::blend_used(&mut row, inputs.tex, t.texel, c, used, t.weight, &mut widened);
                    }
                    Some(t) => {
                        let rows = S::rows(inputs.tex, t.texel, c, used, &mut widened);
                        blend(&mut row[..colour], rows, t.weight);
                        blend(&mut row[extra.clone()], rows.map(|r| &r[extra.start..]), t.weight);
                        texel_slopes(&mut d_fx[..colour], &mut d_fy[..colour], rows, t);
                        let shifted = rows.map(|r| &r[extra.start..]);
                        texel_slopes(&mut d_fx[extra.clone()], &mut d_fy[extra.clone()], shifted, t);
                    }
                    None => {
                        for buf in [&mut row, &mut d_fx, &mut d_fy] {
                            buf[..colour].fill(T::zero());
                            buf[extra.clone()].fill(T::zero());
                        }
                    }
                }
                let (b, _) = sh_basis(inputs.degree, direction(inputs.dirs, first + i), false);
                let rgb = sh_sum(&b, &row[..colour], T::c(0.5));
                for ch in 0..3 {
                    // NaN-safe clamp, as the shading op: a NaN coefficient gives NaN.
                    out[ch].write(if rgb[ch] < T::zero() { T::zero() } else { rgb[ch] });
                }
                if let Some(extra_out) = extra_out.as_deref_mut() {
                    copy_short(&mut extra_out[e * i..], &row[extra.start..], e);
                }
                if let Some(raw) = raw.as_deref_mut() {
                    copy_short(&mut raw[3 * i..], &rgb, 3);
                }
                if let Some(s) = slope_out.as_deref_mut() {
                    let s = &mut s[2 * width * i..2 * width * (i + 1)];
                    let (along_u, along_v) = s.split_at_mut(width);
                    let (su, sv) = (
                        sh_sum(&b, &d_fx[..colour], T::zero()),
                        sh_sum(&b, &d_fy[..colour], T::zero()),
                    );
                    for ch in 0..3 {
                        along_u[ch].write(su[ch] * du);
                        along_v[ch].write(sv[ch] * dv);
                    }
                    for (j, k) in extra.clone().enumerate() {
                        along_u[3 + j].write(d_fx[k] * du);
                        along_v[3 + j].write(d_fy[k] * dv);
                    }
                }
            }
            // SAFETY: the loop wrote each sample's colour and extra channels.
            let (rgb_out, extra_out) = unsafe {
                let extra_out = extra_out.as_deref().unwrap_or(&[]);
                (written_part(rgb_out), written_part(extra_out))
            };
            // x·0 ≠ 0 exactly for NaN and ±inf (an OR-reduction vectorises).
            (rgb_out.iter().chain(extra_out)).fold(false, |bad, &x| bad | (x * T::zero() != T::zero()))
        })
        .reduce(|| false, |a, b| a | b);
    if non_finite {
        S::check_finite("tex", inputs.tex)?;
    }
    // SAFETY: the chunks partition the samples, and the loop wrote every sample's colour,
    // extra channels, pre-clamp colour and both slopes (3 + E values each).
    unsafe {
        Ok(ShTextureOutput {
            rgb: assume_written(rgb),
            extra: assume_written(extra_out),
            raw_rgb: raw.map(|raw| assume_written(raw)),
            slopes: slope_out.map(|slopes| assume_written(slopes)),
        })
    }
}

/// Adjoint of [`sh_texture_forward`]: the rows' gradient (with `need_rows`) and, when the
/// slopes are given, the UV gradient. Colour channels clamped at 0 (a pre-clamp value
/// below 0, or NaN) pass no gradient.
pub fn sh_texture_backward<T: Real>(
    g: &ShTextureGradInputs<'_, T>,
    need_rows: bool,
) -> Result<ShTextureGrads<T>> {
    let colour = check_channels(g.degree, g.channels, &g.extra)?;
    let (c, extra) = (g.channels, g.extra.clone());
    let (e, width) = (extra.len(), 3 + extra.len());
    let n = g.uv.len() / 2;
    check_len("uv", g.uv, 2 * n, "(N, 2)")?;
    check_len("dirs", g.dirs, 3 * n, &format!("(N, 3) = ({n}, 3)"))?;
    check_len("raw_rgb", g.raw_rgb, 3 * n, &format!("(N, 3) = ({n}, 3)"))?;
    if let Some(v) = g.v_rgb {
        check_len("v_rgb", v, 3 * n, &format!("(N, 3) = ({n}, 3)"))?;
    }
    if let Some(v) = g.v_extra {
        check_len("v_extra", v, e * n, &format!("(N, E) = ({n}, {e})"))?;
    }
    if let Some(s) = g.slopes {
        check_len(
            "slopes",
            s,
            2 * width * n,
            &format!("(N, 2, 3 + E) = ({n}, 2, {width})"),
        )?;
    }
    let mut v_rows = need_rows
        .then(|| unwritten("sh_texture row gradient (N, C)", n * c))
        .transpose()?;
    let mut v_uv = g
        .slopes
        .map(|_| zeroed("sh_texture uv gradient (N, 2)", 2 * n))
        .transpose()?;
    // A part without a gradient reads as zeros, as autograd would have filled them.
    let no_extra = vec![T::zero(); e];
    let tasks = n.div_ceil(SAMPLE_CHUNK);
    let row_chunks = optional_chunks(v_rows.as_deref_mut(), SAMPLE_CHUNK * c, tasks);
    let uv_chunks = optional_chunks(v_uv.as_deref_mut(), SAMPLE_CHUNK * 2, tasks);
    row_chunks
        .into_par_iter()
        .zip(uv_chunks)
        .enumerate()
        .for_each(|(chunk, (mut rows, mut v_uv))| {
            let first = chunk * SAMPLE_CHUNK;
            let count = SAMPLE_CHUNK.min(n - first);
            for i in 0..count {
                let s = first + i;
                let given = g
                    .v_rgb
                    .map_or([T::zero(); 3], |v| [v[3 * s], v[3 * s + 1], v[3 * s + 2]]);
                let v_extra = g.v_extra.map_or(&no_extra[..], |v| &v[e * s..e * (s + 1)]);
                let raw = &g.raw_rgb[3 * s..3 * s + 3];
                let v_rgb = unclamped([raw[0], raw[1], raw[2]], given);
                if let Some(rows) = rows.as_deref_mut() {
                    let row = &mut rows[c * i..c * (i + 1)];
                    let (b, _) = sh_basis(g.degree, direction(g.dirs, s), false);
                    sh_sum_adjoint(&b, v_rgb, &mut row[..colour]);
                    // Zeros past the colour, then the extra channels (after the colour when
                    // there are any) over theirs: every channel of the row is written.
                    write_zeros(&mut row[colour..]);
                    copy_short(&mut row[extra.start..], v_extra, e);
                }
                if let (Some(v_uv), Some(slopes)) = (v_uv.as_deref_mut(), g.slopes) {
                    if !(g.uv[2 * s].is_finite() && g.uv[2 * s + 1].is_finite()) {
                        continue; // read zeros: no UV gradient, as the lookup
                    }
                    let (along_u, along_v) = slopes[2 * width * s..2 * width * (s + 1)].split_at(width);
                    let (mut du, mut dv) = (T::zero(), T::zero());
                    for j in 0..width {
                        let x = if j < 3 { v_rgb[j] } else { v_extra[j - 3] };
                        du += x * along_u[j];
                        dv += x * along_v[j];
                    }
                    v_uv[2 * i] = du;
                    v_uv[2 * i + 1] = dv;
                }
            }
        });
    // SAFETY: the chunks partition the rows, and each chunk's loop wrote every row of it.
    let v_rows = v_rows.map(|rows| unsafe { assume_written(rows) });
    Ok(ShTextureGrads { v_rows, v_uv })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{texture_backward, texture_forward};
    use crate::shading::{shade_backward, shade_forward, ShadingInputs};
    use crate::testing::{on_threads, Rng};

    const H: usize = 9;
    const W: usize = 7;
    const C: usize = 56;

    /// A texture, UVs (some outside the texel centres, one NaN) and unit directions.
    fn scene(n: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut rng = Rng::new(seed);
        let tex = rng.vec(H * W * C, -1.0, 1.0);
        let mut uv = rng.vec(2 * n, -0.05, 1.05);
        uv[6] = f64::NAN;
        let dirs = (0..n)
            .flat_map(|_| {
                let d: [f64; 3] = std::array::from_fn(|_| rng.uniform(-1.0, 1.0));
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                d.map(|x| x / len)
            })
            .collect();
        (tex, uv, dirs)
    }

    fn inputs<'a>(tex: &'a [f64], uv: &'a [f64], dirs: &'a [f64], degree: usize) -> ShTextureInputs<'a, f64> {
        ShTextureInputs {
            tex,
            height: H,
            width: W,
            channels: C,
            uv,
            dirs,
            degree,
            extra: 48..51,
        }
    }

    /// Both gradients of `v_values (N, 3 + E)`, the colour's then the extra channels', after
    /// the forward `out` of `inputs`.
    fn backward<T: Real>(
        inputs: &ShTextureInputs<'_, T>,
        out: &ShTextureOutput<T>,
        v_values: &[T],
    ) -> ShTextureGrads<T> {
        let e = inputs.extra.len();
        let v_rgb: Vec<T> = v_values.chunks(3 + e).flat_map(|v| v[..3].to_vec()).collect();
        let v_extra: Vec<T> = v_values.chunks(3 + e).flat_map(|v| v[3..].to_vec()).collect();
        let grad_inputs = ShTextureGradInputs {
            uv: inputs.uv,
            dirs: inputs.dirs,
            degree: inputs.degree,
            channels: inputs.channels,
            extra: inputs.extra.clone(),
            raw_rgb: out.raw_rgb.as_deref().unwrap(),
            slopes: out.slopes.as_deref(),
            v_rgb: Some(&v_rgb),
            v_extra: Some(&v_extra),
        };
        sh_texture_backward(&grad_inputs, true).unwrap()
    }

    #[test]
    fn values_and_row_gradient_are_the_lookup_then_shading_bit_for_bit() {
        let n = 5000; // more than one chunk
        let (tex, uv, dirs) = scene(n, 1);
        for degree in 0..=3 {
            let out = sh_texture_forward(&inputs(&tex, &uv, &dirs, degree), true, true).unwrap();
            let rows = texture_forward(&tex, H, W, C, &uv).unwrap();
            let shading = ShadingInputs {
                coeffs: &rows,
                dirs: &dirs,
                stride: C,
                degree,
            };
            let rgb = shade_forward(&shading).unwrap();
            let v_values = Rng::new(2).vec::<f64>(6 * n, -1.0, 1.0);
            let grads = backward(&inputs(&tex, &uv, &dirs, degree), &out, &v_values);
            let v_rgb: Vec<f64> = v_values.chunks(6).flat_map(|v| v[..3].to_vec()).collect();
            let mut expected_rows = shade_backward(&shading, &v_rgb, None).unwrap();
            for s in 0..n {
                expected_rows[s * C + 48..s * C + 51].copy_from_slice(&v_values[6 * s + 3..6 * s + 6]);
                assert_eq!(
                    out.rgb[3 * s..3 * s + 3],
                    rgb[3 * s..3 * s + 3],
                    "degree {degree}"
                );
                assert_eq!(out.extra[3 * s..3 * s + 3], rows[s * C + 48..s * C + 51]);
            }
            assert_eq!(grads.v_rows.as_deref().unwrap(), &expected_rows[..]);
            // The UV gradient, through the slopes, against the lookup's own.
            let lookup = texture_backward(&tex, H, W, C, &uv, &expected_rows, false, true).unwrap();
            let (got, want) = (grads.v_uv.unwrap(), lookup.v_uv.unwrap());
            for (a, b) in got.iter().zip(&want) {
                assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "uv gradient {a} vs {b}");
            }
            assert_eq!(&got[6..8], &[0.0, 0.0], "a NaN coordinate passes no UV gradient");
        }
    }

    #[test]
    fn same_bits_for_any_thread_count() {
        let n = 7000;
        let (tex, uv, dirs) = scene(n, 3);
        let tex: Vec<f32> = tex.iter().map(|&x| x as f32).collect();
        let uv: Vec<f32> = uv.iter().map(|&x| x as f32).collect();
        let dirs: Vec<f32> = dirs.iter().map(|&x| x as f32).collect();
        let v_values = Rng::new(4).vec::<f32>(6 * n, -1.0, 1.0);
        let run = || {
            let inputs = ShTextureInputs {
                tex: &tex,
                height: H,
                width: W,
                channels: C,
                uv: &uv,
                dirs: &dirs,
                degree: 3,
                extra: 48..51,
            };
            let out = sh_texture_forward(&inputs, true, true).unwrap();
            let grads = backward(&inputs, &out, &v_values);
            (out.rgb, out.extra, out.slopes, grads.v_rows, grads.v_uv)
        };
        let one = on_threads(1, run);
        for threads in [2, 3] {
            assert!(on_threads(threads, run) == one, "{threads} threads");
        }
    }

    /// A part whose gradient is not given (autograd's `None` when the loss does not use
    /// it) gives the gradients of zeros for it, bit for bit.
    #[test]
    fn a_part_without_gradient_is_zeros() {
        let n = 300;
        let (tex, uv, dirs) = scene(n, 7);
        let inputs = inputs(&tex, &uv, &dirs, 3);
        let out = sh_texture_forward(&inputs, true, true).unwrap();
        let v = Rng::new(8).vec::<f64>(3 * n, -1.0, 1.0);
        let zeros = vec![0.0; 3 * n];
        let backward = |v_rgb: Option<&[f64]>, v_extra: Option<&[f64]>| {
            let g = ShTextureGradInputs {
                uv: &uv,
                dirs: &dirs,
                degree: 3,
                channels: C,
                extra: 48..51,
                raw_rgb: out.raw_rgb.as_deref().unwrap(),
                slopes: out.slopes.as_deref(),
                v_rgb,
                v_extra,
            };
            sh_texture_backward(&g, true)
        };
        let run = |v_rgb, v_extra| {
            let grads = backward(v_rgb, v_extra).unwrap();
            (grads.v_rows.unwrap(), grads.v_uv.unwrap())
        };
        assert_eq!(run(Some(&v), None), run(Some(&v), Some(&zeros)));
        assert_eq!(run(None, Some(&v)), run(Some(&zeros), Some(&v)));
        let short = &v[..3 * n - 1];
        assert!(backward(None, Some(short))
            .unwrap_err()
            .to_string()
            .contains("v_extra"));
    }

    #[test]
    fn optional_outputs_only_when_asked() {
        let (tex, uv, dirs) = scene(10, 5);
        let out = sh_texture_forward(&inputs(&tex, &uv, &dirs, 3), false, false).unwrap();
        assert!(out.raw_rgb.is_none() && out.slopes.is_none());
        let full = sh_texture_forward(&inputs(&tex, &uv, &dirs, 3), true, true).unwrap();
        assert_eq!((&out.rgb, &out.extra), (&full.rgb, &full.extra));
        assert_eq!(&out.rgb[9..12], &[0.5, 0.5, 0.5], "a NaN coordinate reads zeros");
        assert_eq!(&out.extra[9..12], &[0.0, 0.0, 0.0]);
    }

    #[test]
    fn bad_inputs_are_named() {
        let (mut tex, uv, mut dirs) = scene(10, 6);
        let message = |e: Error| e.to_string();
        let mut bad = inputs(&tex, &uv, &dirs, 3);
        bad.extra = 40..51;
        assert!(message(sh_texture_forward(&bad, false, false).unwrap_err()).contains("extra"));
        let mut bad = inputs(&tex, &uv, &dirs, 4);
        bad.extra = 60..61;
        assert!(message(sh_texture_forward(&bad, false, false).unwrap_err()).contains("degree"));
        let short = &dirs[..27];
        assert!(
            message(sh_texture_forward(&inputs(&tex, &uv, short, 3), false, false).unwrap_err())
                .contains("dirs")
        );
        dirs[4] = f64::INFINITY;
        assert!(
            message(sh_texture_forward(&inputs(&tex, &uv, &dirs, 3), false, false).unwrap_err())
                .contains("dirs")
        );
        dirs[4] = 0.0;
        // A non-finite texel the samples read is named.
        for t in tex.iter_mut().take(C) {
            *t = f64::NAN;
        }
        let uv0 = [0.0, 1.0];
        let err = sh_texture_forward(&inputs(&tex, &uv0, &dirs[..3], 3), false, false).unwrap_err();
        assert!(message(err).contains("tex"));
    }
}
