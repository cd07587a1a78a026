//! Eight-lane arithmetic for the per-pixel compositing loops.
//!
//! The compositing code is written once over [`Lanes`] and instantiated three times:
//! [`Avx2`] (explicit AVX2/FMA), [`Emu<f32>`] (plain scalar code doing the same lane-wise
//! operations in the same order) and [`Emu<f64>`] (references and finite differences).
//! Every operation is correctly rounded per lane and the exponential is one fixed
//! polynomial, so the AVX2 and scalar float32 paths produce the same bits, decisions
//! included — the tests check it.

use crate::Real;

/// Number of pixels processed together.
pub const WIDTH: usize = 8;

/// The per-lane float operations the compositor needs. `min`/`max` follow the x86 rule
/// (`min(a, b) = if a < b { a } else { b }`), so a NaN operand yields `b`.
pub trait Lanes: Copy + Send + Sync {
    type Elem: Real;
    type Mask: Copy;

    fn splat(x: Self::Elem) -> Self;
    fn from_array(a: [Self::Elem; WIDTH]) -> Self;
    fn to_array(self) -> [Self::Elem; WIDTH];
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    /// `self · b + c` with one rounding.
    fn mul_add(self, b: Self, c: Self) -> Self;
    fn min(self, o: Self) -> Self;
    /// Correctly rounded square root (NaN for negative lanes).
    fn sqrt(self) -> Self;
    /// `exp(self)` for `self ≤ 0`; inputs below −87 are treated as −87 (the result is far
    /// below every threshold that uses it).
    fn exp_nonpositive(self) -> Self;
    /// Lane-wise `self >= o` (false when either is NaN).
    fn ge(self, o: Self) -> Self::Mask;
    /// Lane-wise `self <= o` (false when either is NaN).
    fn le(self, o: Self) -> Self::Mask;
    /// Lane-wise `self > o` (false when either is NaN).
    fn gt(self, o: Self) -> Self::Mask;
    fn and(a: Self::Mask, b: Self::Mask) -> Self::Mask;
    /// `a & !b`
    fn and_not(a: Self::Mask, b: Self::Mask) -> Self::Mask;
    fn mask_from_bits(bits: u8) -> Self::Mask;
    fn mask_bits(m: Self::Mask) -> u8;
    /// `if m { a } else { b }` per lane.
    fn select(m: Self::Mask, a: Self, b: Self) -> Self;
    /// Sum of the lanes in a fixed tree: ((l0+l4)+(l2+l6)) + ((l1+l5)+(l3+l7)).
    fn sum(self) -> Self::Elem;
}

/// The scalar exponential shared by every float32 path (Cephes-style range reduction
/// and degree-5 polynomial; relative error ≈ 2e-7 on [−87, 0]).
pub trait KernelExp: Real {
    fn exp_nonpositive(x: Self) -> Self;
}

const EXP_MIN: f32 = -87.0;
const LOG2E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const EXP_POLY: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];

impl KernelExp for f32 {
    #[inline(always)]
    fn exp_nonpositive(x: f32) -> f32 {
        let x = if x > EXP_MIN { x } else { EXP_MIN };
        let n = (x * LOG2E).round_ties_even();
        let r = n.mul_add(-LN2_HI, x);
        let r = n.mul_add(-LN2_LO, r);
        let mut p = EXP_POLY[0];
        for c in &EXP_POLY[1..] {
            p = p.mul_add(r, *c);
        }
        let r2 = r * r;
        let p = p.mul_add(r2, r) + 1.0;
        p * f32::from_bits(((n as i32 + 127) as u32) << 23)
    }
}

impl KernelExp for f64 {
    #[inline(always)]
    fn exp_nonpositive(x: f64) -> f64 {
        x.exp()
    }
}

/// Lanes emulated with scalar code: the reference ordering of every operation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Emu<T>(pub [T; WIDTH]);

impl<T: Real + KernelExp> Lanes for Emu<T> {
    type Elem = T;
    type Mask = u8;

    #[inline(always)]
    fn splat(x: T) -> Self {
        Self([x; WIDTH])
    }
    #[inline(always)]
    fn from_array(a: [T; WIDTH]) -> Self {
        Self(a)
    }
    #[inline(always)]
    fn to_array(self) -> [T; WIDTH] {
        self.0
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Self(std::array::from_fn(|i| self.0[i] + o.0[i]))
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Self(std::array::from_fn(|i| self.0[i] - o.0[i]))
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        Self(std::array::from_fn(|i| self.0[i] * o.0[i]))
    }
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        Self(std::array::from_fn(|i| self.0[i].mul_add(b.0[i], c.0[i])))
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        Self(std::array::from_fn(|i| {
            if self.0[i] < o.0[i] {
                self.0[i]
            } else {
                o.0[i]
            }
        }))
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        Self(self.0.map(T::sqrt))
    }
    #[inline(always)]
    fn exp_nonpositive(self) -> Self {
        Self(self.0.map(T::exp_nonpositive))
    }
    #[inline(always)]
    fn ge(self, o: Self) -> u8 {
        bits(|i| self.0[i] >= o.0[i])
    }
    #[inline(always)]
    fn le(self, o: Self) -> u8 {
        bits(|i| self.0[i] <= o.0[i])
    }
    #[inline(always)]
    fn gt(self, o: Self) -> u8 {
        bits(|i| self.0[i] > o.0[i])
    }
    #[inline(always)]
    fn and(a: u8, b: u8) -> u8 {
        a & b
    }
    #[inline(always)]
    fn and_not(a: u8, b: u8) -> u8 {
        a & !b
    }
    #[inline(always)]
    fn mask_from_bits(bits: u8) -> u8 {
        bits
    }
    #[inline(always)]
    fn mask_bits(m: u8) -> u8 {
        m
    }
    #[inline(always)]
    fn select(m: u8, a: Self, b: Self) -> Self {
        Self(std::array::from_fn(
            |i| if m >> i & 1 == 1 { a.0[i] } else { b.0[i] },
        ))
    }
    #[inline(always)]
    fn sum(self) -> T {
        let v = self.0;
        let q: [T; 4] = std::array::from_fn(|i| v[i] + v[i + 4]);
        let h = [q[0] + q[2], q[1] + q[3]];
        h[0] + h[1]
    }
}

#[inline(always)]
fn bits(f: impl Fn(usize) -> bool) -> u8 {
    (0..WIDTH).fold(0u8, |acc, i| acc | (f(i) as u8) << i)
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
pub use avx2::Avx2;

/// Explicit AVX2/FMA lanes. Compiled when the build targets AVX2 + FMA (the workspace
/// default, x86-64-v3); the intrinsics are then safe to call.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{Lanes, EXP_MIN, EXP_POLY, LN2_HI, LN2_LO, LOG2E, WIDTH};

    #[derive(Clone, Copy, Debug)]
    pub struct Avx2(__m256);

    // SAFETY: a plain bundle of eight floats.
    unsafe impl Send for Avx2 {}
    unsafe impl Sync for Avx2 {}

    impl Lanes for Avx2 {
        type Elem = f32;
        type Mask = __m256;

        #[inline(always)]
        fn splat(x: f32) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_set1_ps(x)) }
        }
        #[inline(always)]
        fn from_array(a: [f32; WIDTH]) -> Self {
            // SAFETY: `a` holds exactly eight floats; unaligned load.
            Self(unsafe { _mm256_loadu_ps(a.as_ptr()) })
        }
        #[inline(always)]
        fn to_array(self) -> [f32; WIDTH] {
            let mut a = [0.0f32; WIDTH];
            // SAFETY: `a` has room for eight floats; unaligned store.
            unsafe { _mm256_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_add_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_sub_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_mul_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn mul_add(self, b: Self, c: Self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_fmadd_ps(self.0, b.0, c.0)) }
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_min_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_sqrt_ps(self.0)) }
        }
        #[inline(always)]
        fn exp_nonpositive(self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe {
                // `max(x, EXP_MIN)` with x first: a NaN input yields EXP_MIN, as in the scalar code.
                let x = _mm256_max_ps(self.0, _mm256_set1_ps(EXP_MIN));
                let n = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(_mm256_mul_ps(
                    x,
                    _mm256_set1_ps(LOG2E),
                ));
                let r = _mm256_fmadd_ps(n, _mm256_set1_ps(-LN2_HI), x);
                let r = _mm256_fmadd_ps(n, _mm256_set1_ps(-LN2_LO), r);
                let mut p = _mm256_set1_ps(EXP_POLY[0]);
                for c in &EXP_POLY[1..] {
                    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(*c));
                }
                let r2 = _mm256_mul_ps(r, r);
                let p = _mm256_add_ps(_mm256_fmadd_ps(p, r2, r), _mm256_set1_ps(1.0));
                let e =
                    _mm256_slli_epi32::<23>(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)));
                Self(_mm256_mul_ps(p, _mm256_castsi256_ps(e)))
            }
        }
        #[inline(always)]
        fn ge(self, o: Self) -> __m256 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { _mm256_cmp_ps::<_CMP_GE_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn le(self, o: Self) -> __m256 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { _mm256_cmp_ps::<_CMP_LE_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> __m256 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { _mm256_cmp_ps::<_CMP_GT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn and(a: __m256, b: __m256) -> __m256 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { _mm256_and_ps(a, b) }
        }
        #[inline(always)]
        fn and_not(a: __m256, b: __m256) -> __m256 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { _mm256_andnot_ps(b, a) }
        }
        #[inline(always)]
        fn mask_from_bits(bits: u8) -> __m256 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe {
                let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
                let set = _mm256_and_si256(_mm256_set1_epi32(bits as i32), lane_bits);
                _mm256_castsi256_ps(_mm256_cmpeq_epi32(set, lane_bits))
            }
        }
        #[inline(always)]
        fn mask_bits(m: __m256) -> u8 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { _mm256_movemask_ps(m) as u8 }
        }
        #[inline(always)]
        fn select(m: __m256, a: Self, b: Self) -> Self {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe { Self(_mm256_blendv_ps(b.0, a.0, m)) }
        }
        #[inline(always)]
        fn sum(self) -> f32 {
            // SAFETY: compiled only when AVX2 and FMA are enabled for the target.
            unsafe {
                let lo = _mm256_castps256_ps128(self.0);
                let hi = _mm256_extractf128_ps::<1>(self.0);
                let q = _mm_add_ps(lo, hi); // l_i + l_{i+4}
                let h = _mm_add_ps(q, _mm_movehl_ps(q, q)); // (q0+q2, q1+q3, ..)
                _mm_cvtss_f32(_mm_add_ss(h, _mm_shuffle_ps::<1>(h, h)))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernel_exp_is_accurate_on_its_range() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -87.0 * i as f64 / 200_000.0;
            let got = f32::exp_nonpositive(x as f32) as f64;
            let want = (x as f32 as f64).exp();
            worst = worst.max(((got - want) / want).abs());
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        assert_eq!(f32::exp_nonpositive(0.0), 1.0);
        assert!(f32::exp_nonpositive(-1e30) > 0.0);
        assert!(f32::exp_nonpositive(f32::NAN).is_finite());
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
    #[test]
    fn avx2_matches_emulation_bitwise() {
        let mut rng = crate::testing::Rng::new(5);
        for _ in 0..2000 {
            let a: [f32; 8] = std::array::from_fn(|_| rng.uniform(-100.0, 5.0) as f32);
            let b: [f32; 8] = std::array::from_fn(|_| rng.uniform(-3.0, 3.0) as f32);
            let (ea, eb) = (Emu(a), Emu(b));
            let (va, vb) = (Avx2::from_array(a), Avx2::from_array(b));
            let same = |e: Emu<f32>, v: Avx2| e.0.map(f32::to_bits) == v.to_array().map(f32::to_bits);
            assert!(same(ea.exp_nonpositive(), va.exp_nonpositive()));
            assert!(same(ea.mul_add(eb, ea), va.mul_add(vb, va)));
            assert!(same(ea.min(eb), va.min(vb)));
            assert!(same(ea.sqrt(), va.sqrt()));
            assert_eq!(Emu::<f32>::mask_bits(ea.ge(eb)), Avx2::mask_bits(va.ge(vb)));
            assert_eq!(ea.sum().to_bits(), va.sum().to_bits());
            let m = (rng.next_u64() & 0xff) as u8;
            assert_eq!(Avx2::mask_bits(Avx2::mask_from_bits(m)), m);
            assert!(same(
                Emu::<f32>::select(m, ea, eb),
                Avx2::select(Avx2::mask_from_bits(m), va, vb)
            ));
        }
        let nan = [f32::NAN; 8];
        let e = Emu(nan).min(Emu::splat(0.99));
        let v = Avx2::from_array(nan).min(Avx2::splat(0.99));
        assert_eq!(e.0, v.to_array());
    }
}
