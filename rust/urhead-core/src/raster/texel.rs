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
