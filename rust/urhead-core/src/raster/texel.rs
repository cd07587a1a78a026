//! How a lookup reads its texture's texels: in the lookup's own float type, or stored as
//! IEEE float16 (`half::f16`) and widened to f32 as they are read.
//!
//! Why float16: a frozen texture read many times (a rendered avatar's 2048² × 56 maps) is
//! read at random rows, and on this kind of machine such reads cost per cache line, so
//! half the bytes is close to half the time. float16 rather than bfloat16: its 11-bit
//! significand keeps a value to 2⁻¹¹ relative (an SH colour near 1 to ~5e-4, an eighth of
//! an 8-bit step), where bfloat16's 8 bits would be a visible 4e-3; its range (±65504)
//! is checked by whoever makes the copy (NUMERICS.md case 34).

use std::ops::Range;

use half::f16;
use half::slice::HalfFloatSliceExt;

use super::texture::blend;
use crate::error::{check_finite, Error, Result};
use crate::Real;

/// A texture's element type as lookups computing in `T` read it.
pub trait Texel<T: Real>: Copy + Send + Sync + 'static {
    /// The rows `texel` of `tex (…, c)` as `T`, valid at least on the channels in `used`:
    /// the rows themselves, or those channels widened into `scratch (4·c)`.
    fn rows<'a>(
        tex: &'a [Self],
        texel: [u32; 4],
        c: usize,
        used: [&Range<usize>; 2],
        scratch: &'a mut [T],
    ) -> [&'a [T]; 4];

    /// The bilinear blend of the rows `texel` with weights `w` on the channels in `used`,
    /// written into `out (c)` there: [`blend`] of [`Texel::rows`], bit for bit, where a
    /// lookup needs no rows besides (no slopes).
    #[inline(always)]
    fn blend_used(
        out: &mut [T],
        tex: &[Self],
        texel: [u32; 4],
        c: usize,
        used: [&Range<usize>; 2],
        w: [T; 4],
        scratch: &mut [T],
    ) {
        let rows = Self::rows(tex, texel, c, used, scratch);
        for range in used {
            blend(&mut out[range.clone()], rows.map(|r| &r[range.clone()]), w);
        }
    }

    /// An error naming the first non-finite value of `tex`, if any (the lazy check a
    /// lookup makes when a value came out non-finite).
    fn check_finite(arg: &'static str, tex: &[Self]) -> Result<()>;
}

impl<T: Real> Texel<T> for T {
    #[inline(always)]
    fn rows<'a>(
        tex: &'a [T],
        texel: [u32; 4],
        c: usize,
        _used: [&Range<usize>; 2],
        _scratch: &'a mut [T],
    ) -> [&'a [T]; 4] {
        texel.map(|k| &tex[k as usize * c..(k as usize + 1) * c])
    }

    fn check_finite(arg: &'static str, tex: &[T]) -> Result<()> {
        check_finite(arg, tex)
    }
}

impl Texel<f32> for f16 {
    #[inline(always)]
    fn rows<'a>(
        tex: &'a [f16],
        texel: [u32; 4],
        c: usize,
        used: [&Range<usize>; 2],
        scratch: &'a mut [f32],
    ) -> [&'a [f32]; 4] {
        for (row, k) in scratch.chunks_exact_mut(c).zip(texel) {
            let src = &tex[k as usize * c..(k as usize + 1) * c];
            for range in used {
                // Exact (every float16 is an f32); SIMD (F16C) where the CPU has it.
                src[range.clone()].convert_to_f32_slice(&mut row[range.clone()]);
            }
        }
        let scratch: &'a [f32] = scratch;
        std::array::from_fn(|i| &scratch[i * c..(i + 1) * c])
    }

    /// Widened in registers as they are blended (eight channels at a time with F16C), with
    /// no scratch rows written and read back: the same operations on the same values.
    #[inline(always)]
    fn blend_used(
        out: &mut [f32],
        tex: &[f16],
        texel: [u32; 4],
        c: usize,
        used: [&Range<usize>; 2],
        w: [f32; 4],
        _scratch: &mut [f32],
    ) {
        for range in used {
            let rows = texel.map(|k| &tex[k as usize * c + range.start..k as usize * c + range.end]);
            blend_float16(&mut out[range.clone()], rows, w);
        }
    }

    fn check_finite(arg: &'static str, tex: &[f16]) -> Result<()> {
        match tex.iter().position(|x| !x.is_finite()) {
            None => Ok(()),
            Some(index) => Err(Error::NonFinite {
                arg,
                index,
                value: tex[index].to_f64(),
            }),
        }
    }
}

/// [`blend`] of float16 rows widened to f32: `w0·a + w1·b + w2·c + w3·d`, left to right,
/// each product and sum rounded to f32 as there (no fused multiply-add).
#[inline(always)]
fn blend_float16(out: &mut [f32], rows: [&[f16]; 4], w: [f32; 4]) {
    let n = out.len();
    let rows = rows.map(|r| &r[..n]); // every row covers the output
    let mut done = 0;
    #[cfg(all(target_arch = "x86_64", target_feature = "f16c", target_feature = "avx"))]
    {
        use std::arch::x86_64::{
            __m128i, _mm256_add_ps, _mm256_cvtph_ps, _mm256_mul_ps, _mm256_set1_ps, _mm256_storeu_ps,
            _mm_loadu_si128,
        };
        // SAFETY: F16C and AVX are enabled at compile time (cfg above); every load reads 8
        // halves of a row and every store 8 floats of `out` at `done + 8 ≤ n`, in bounds.
        unsafe {
            let weights = w.map(|x| _mm256_set1_ps(x));
            while done + 8 <= n {
                let r =
                    rows.map(|r| _mm256_cvtph_ps(_mm_loadu_si128(r.as_ptr().add(done) as *const __m128i)));
                let sum = _mm256_add_ps(
                    _mm256_add_ps(
                        _mm256_add_ps(_mm256_mul_ps(weights[0], r[0]), _mm256_mul_ps(weights[1], r[1])),
                        _mm256_mul_ps(weights[2], r[2]),
                    ),
                    _mm256_mul_ps(weights[3], r[3]),
                );
                _mm256_storeu_ps(out.as_mut_ptr().add(done), sum);
                done += 8;
            }
        }
    }
    // The tail (and everything without F16C), widened a block at a time and blended by
    // `blend` itself.
    for start in (done..n).step_by(TAIL_BLOCK) {
        let len = TAIL_BLOCK.min(n - start);
        let mut widened = [[0f32; TAIL_BLOCK]; 4];
        for (dst, row) in widened.iter_mut().zip(rows) {
            row[start..start + len].convert_to_f32_slice(&mut dst[..len]);
        }
        blend(
            &mut out[start..start + len],
            widened.each_ref().map(|r| &r[..len]),
            w,
        );
    }
}

/// Channels widened at a time by [`blend_float16`]'s scalar part.
const TAIL_BLOCK: usize = 8;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn float16_rows_widen_the_used_channels_exactly() {
        let c = 5;
        let values = [0.0, 1.0, -2.5, 65504.0, 6.0e-8, 3.0e-5, 0.333, -0.1, 7.0, 1.0e4];
        let tex: Vec<f16> = (0..4 * c)
            .map(|i| f16::from_f32(values[i % values.len()]))
            .collect();
        let mut scratch = vec![f32::NAN; 4 * c];
        let rows = <f16 as Texel<f32>>::rows(&tex, [3, 0, 2, 1], c, [&(0..2), &(3..5)], &mut scratch);
        for (row, k) in rows.iter().zip([3usize, 0, 2, 1]) {
            for ch in [0, 1, 3, 4] {
                assert_eq!(row[ch].to_bits(), tex[k * c + ch].to_f32().to_bits());
            }
            assert!(row[2].is_nan(), "an unused channel is not read");
        }
    }

    #[test]
    fn float16_blend_is_the_blend_of_the_widened_rows_bit_for_bit() {
        let c = 61; // eight-channel groups and a tail of 5
        let mut rng = crate::testing::Rng::new(3);
        let mut tex: Vec<f16> = (0..6 * c)
            .map(|_| f16::from_f64(rng.uniform(-4.0, 4.0)))
            .collect();
        // Subnormal, zero, largest and non-finite halves pass through as data.
        tex[2] = f16::from_f32(6.0e-8);
        tex[c + 9] = f16::NEG_ZERO;
        tex[2 * c + 17] = f16::MAX;
        tex[3 * c + 60] = f16::NAN;
        tex[4 * c + 33] = f16::INFINITY;
        let texel = [4, 1, 3, 2];
        let used = [&(0..48), &(50..61)];
        for w in [
            [0.25f32, 0.25, 0.25, 0.25],
            [0.7, 0.1, 0.15, 0.05],
            [1.0, 0.0, 0.0, 0.0],
        ] {
            let mut widened = vec![0f32; 4 * c];
            let rows = <f16 as Texel<f32>>::rows(&tex, texel, c, used, &mut widened);
            let mut want = vec![f32::NAN; c];
            for range in used {
                blend(&mut want[range.clone()], rows.map(|r| &r[range.clone()]), w);
            }
            let mut got = vec![f32::NAN; c];
            <f16 as Texel<f32>>::blend_used(&mut got, &tex, texel, c, used, w, &mut widened);
            let bits = |x: &[f32]| x.iter().map(|y| y.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "weights {w:?}");
            assert!(
                got[48..50].iter().all(|x| x.is_nan()),
                "unused channels are not written"
            );
        }
    }

    #[test]
    fn a_non_finite_float16_texel_is_named() {
        let mut tex = vec![f16::from_f32(1.0); 6];
        assert!(<f16 as Texel<f32>>::check_finite("tex", &tex).is_ok());
        tex[4] = f16::INFINITY;
        let err = <f16 as Texel<f32>>::check_finite("tex", &tex).unwrap_err();
        assert!(
            matches!(
                err,
                Error::NonFinite {
                    arg: "tex",
                    index: 4,
                    ..
                }
            ),
            "{err}"
        );
    }
}
