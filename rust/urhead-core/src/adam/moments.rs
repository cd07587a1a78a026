//! How Adam's moment tables are stored: `f32`, or bfloat16 ([`Bf16`]) at half the bytes.
//!
//! A fit's sparse Adam step is bound by the memory traffic of its three `(N, C)` tables
//! (parameters, first and second moments), so storing both moments in 16 bits moves a
//! third fewer bytes a step and halves the moments' memory (2 × 940 MB → 2 × 470 MB at
//! 2048² × 56). The update itself runs in f32 and only the stored values are rounded:
//!
//! - the first moment to nearest (ties to even): `m ← 0.9·m + 0.1·g` changes by ~10 % a
//!   step where it changes at all, far above bf16's 2⁻⁸ relative spacing;
//! - the second moment **stochastically**: `v ← 0.999·v + 0.001·g²` changes by 0.1 %, less
//!   than half of bf16's spacing, so rounded to nearest `0.999·v` rounds back to `v` and a
//!   texel whose gradient falls to zero would keep its old `v` (and take steps ~30× too
//!   small) forever. Rounded up with probability equal to the remainder's share of the
//!   spacing, `v` is exact in expectation and decays as f32 Adam's does (NUMERICS.md
//!   case 33). The random bits come from a hash of the row and its step count, so a step
//!   is the same on any number of threads and after a journal's undo.

/// A moment table's element type.
pub trait Moment: Copy + Default + Send + Sync + std::fmt::Debug + 'static {
    /// Largest finite value; a saturating store stays at or below it.
    const MAX: f32;
    /// The stored value as f32 (exact).
    fn load(self) -> f32;
    /// `x` rounded to the nearest stored value, ties to even; NaN stays NaN.
    fn round_nearest(x: f32) -> Self;
    /// `x` rounded down or up to a neighbouring stored value, up with probability equal to
    /// `x`'s remainder's share of the spacing, given 16 uniformly random bits in
    /// `random & 0xFFFF` (exact for types that hold every f32); NaN stays NaN.
    fn round_stochastic(x: f32, random: u32) -> Self;
    /// [`Moment::round_nearest`] without the NaN test: the same value for every `x` but
    /// NaN, whose result is unspecified.
    #[inline(always)]
    fn round_nearest_not_nan(x: f32) -> Self {
        Self::round_nearest(x)
    }
    /// [`Moment::round_stochastic`] without the NaN test: the same value for every `x`
    /// but NaN, whose result is unspecified.
    #[inline(always)]
    fn round_stochastic_not_nan(x: f32, random: u32) -> Self {
        Self::round_stochastic(x, random)
    }
}

impl Moment for f32 {
    const MAX: f32 = f32::MAX;

    #[inline(always)]
    fn load(self) -> f32 {
        self
    }

    #[inline(always)]
    fn round_nearest(x: f32) -> Self {
        x
    }

    #[inline(always)]
    fn round_stochastic(x: f32, _random: u32) -> Self {
        x
    }
}

/// A bfloat16: the upper 16 bits of an f32 (sign, 8-bit exponent, 7-bit mantissa) — the
/// f32's range at 2⁻⁸ relative precision. torch's `bfloat16`, bit for bit.
#[repr(transparent)]
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Bf16(pub u16);

/// A quiet NaN's bits (torch's canonical bfloat16 NaN).
const BF16_NAN: u16 = 0x7FC0;

impl Bf16 {
    /// A table of raw bits (e.g. a torch `bfloat16` tensor viewed as `uint16`) as `Bf16`s.
    pub fn from_bits_mut(bits: &mut [u16]) -> &mut [Bf16] {
        // SAFETY: `Bf16` is `repr(transparent)` over `u16`: same size, alignment and
        // validity, so the slice reinterprets element for element.
        unsafe { std::slice::from_raw_parts_mut(bits.as_mut_ptr().cast(), bits.len()) }
    }

    /// Keeps NaN a NaN: truncating a NaN whose payload sits in the low 16 bits would give ∞.
    #[inline(always)]
    fn finish(x: f32, rounded: u32) -> Self {
        if x.is_nan() {
            Bf16(BF16_NAN)
        } else {
            Self::upper(rounded)
        }
    }

    /// The upper half of a rounded value's bits.
    #[inline(always)]
    fn upper(rounded: u32) -> Self {
        Bf16((rounded >> 16) as u16)
    }

    /// `x`'s bits rounded to nearest, ties to even, in their upper half: adding 0x7FFF plus
    /// the kept part's lowest bit carries exactly when the dropped half exceeds half the
    /// spacing, or equals it and the kept part is odd.
    #[inline(always)]
    fn nearest_bits(x: f32) -> u32 {
        let bits = x.to_bits();
        bits.wrapping_add(0x7FFF + ((bits >> 16) & 1))
    }

    /// `x`'s bits rounded stochastically, in their upper half. Sign and magnitude: adding
    /// r ∈ [0, 2¹⁶) to the magnitude's bits carries into the kept part with probability
    /// (dropped bits) / 2¹⁶ — also across a binade, where the spacing doubles and the
    /// carry lands on the next binade's first value.
    #[inline(always)]
    fn stochastic_bits(x: f32, random: u32) -> u32 {
        x.to_bits().wrapping_add(random & 0xFFFF)
    }
}

impl Moment for Bf16 {
    const MAX: f32 = f32::from_bits(0x7F7F_0000);

    #[inline(always)]
    fn load(self) -> f32 {
        f32::from_bits((self.0 as u32) << 16)
    }

    #[inline(always)]
    fn round_nearest(x: f32) -> Self {
        Self::finish(x, Self::nearest_bits(x))
    }

    #[inline(always)]
    fn round_stochastic(x: f32, random: u32) -> Self {
        Self::finish(x, Self::stochastic_bits(x, random))
    }

    #[inline(always)]
    fn round_nearest_not_nan(x: f32) -> Self {
        Self::upper(Self::nearest_bits(x))
    }

    #[inline(always)]
    fn round_stochastic_not_nan(x: f32, random: u32) -> Self {
        Self::upper(Self::stochastic_bits(x, random))
    }
}

/// 32 random bits for the stochastic rounding of row `row` at its step count `t`: a
/// full-avalanche integer hash (the "lowbias32" constants), so consecutive steps of one
/// row and neighbouring rows are independent.
#[inline(always)]
pub(super) fn row_seed(row: u64, t: i32) -> u32 {
    let mut h = (row as u32) ^ ((row >> 32) as u32).rotate_left(16) ^ (t as u32).wrapping_mul(0x9E37_79B9);
    h ^= h >> 16;
    h = h.wrapping_mul(0x21F0_AAAD);
    h ^= h >> 15;
    h = h.wrapping_mul(0x735A_2D97);
    h ^ (h >> 15)
}

/// The golden-ratio step between channels' seeds, and the multiplier that mixes them.
const CHANNEL_STEP: u32 = 0x9E37_79B9;
const CHANNEL_MIX: u32 = 0x85EB_CA6B;

/// Channel `channel`'s 16 random bits from its row's seed (in the lower half of the
/// result): `(seed + channel·φ)·M`'s upper half. The row update takes them from
/// [`ChannelBits`], the same bits with no multiply in its loop; this is their definition.
#[cfg(test)]
fn channel_random(seed: u32, channel: usize) -> u32 {
    seed.wrapping_add((channel as u32).wrapping_mul(CHANNEL_STEP))
        .wrapping_mul(CHANNEL_MIX)
        >> 16
}

/// `channel_random` for every channel of a row, with both multiplies out of the row's
/// loop: `(seed + channel·φ)·M = seed·M + channel·φ·M` (mod 2³², products distribute), so
/// the channel part is tabulated once per chunk of rows and the row part made once per
/// row. Each channel's bits are then one add and one shift (AVX2 multiplies 32-bit lanes
/// in 2 micro-ops of 10 cycles' latency): the maps' step alone −0.9 ms paired on a real
/// step (faster in 64 of 100).
pub(super) struct ChannelBits(Vec<u32>);

impl ChannelBits {
    pub fn new(channels: usize) -> Self {
        let part = |ch: usize| (ch as u32).wrapping_mul(CHANNEL_STEP).wrapping_mul(CHANNEL_MIX);
        Self((0..channels).map(part).collect())
    }

    /// The row part of a row with seed `seed`, for [`ChannelBits::random`].
    #[inline(always)]
    pub fn row_part(seed: u32) -> u32 {
        seed.wrapping_mul(CHANNEL_MIX)
    }

    /// Per channel, what [`ChannelBits::random`] adds to the row part.
    #[inline(always)]
    pub fn parts(&self) -> &[u32] {
        &self.0
    }

    /// `channel_random(seed, channel)` from `row_part(seed)` and `parts()[channel]`.
    #[inline(always)]
    pub fn random(row_part: u32, channel_part: u32) -> u32 {
        row_part.wrapping_add(channel_part) >> 16
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every value bf16 holds near `x`, from f64 arithmetic: the reference for rounding.
    fn neighbours(x: f32) -> (f32, f32) {
        let down = f32::from_bits(x.to_bits() & 0xFFFF_0000);
        let up = f32::from_bits((x.to_bits() & 0xFFFF_0000) + 0x1_0000);
        (down, up)
    }

    #[test]
    fn nearest_rounding_is_ties_to_even_and_keeps_specials() {
        let cases = [
            0.0f32,
            -0.0,
            1.0,
            1.0 + 2f32.powi(-9),                  // a tie, kept part even: down
            1.0 + 3.0 * 2f32.powi(-9),            // a tie, kept part odd: up
            1.0 + 2f32.powi(-9) + 2f32.powi(-20), // just above a tie: up
            -2.71,
            1e-40, // subnormal
            3.0e38,
            Bf16::MAX,
            f32::MAX, // rounds to ∞, as torch's conversion does
            f32::INFINITY,
            f32::NEG_INFINITY,
        ];
        for x in cases {
            let got = Bf16::round_nearest(x).load();
            let (down, up) = neighbours(x.abs());
            let (down, up) = (down.copysign(x), up.copysign(x));
            // Past the largest finite value IEEE rounding measures to 2¹²⁸ (and gives ∞).
            let up_value = if up.is_infinite() {
                2f64.powi(128).copysign(x as f64)
            } else {
                up as f64
            };
            let (dd, du) = ((x as f64 - down as f64).abs(), (up_value - x as f64).abs());
            let even = if (down.to_bits() >> 16) & 1 == 0 { down } else { up };
            let expected = if x.is_infinite() || dd == 0.0 {
                x
            } else if dd < du {
                down
            } else if du < dd {
                up
            } else {
                even
            };
            assert_eq!(got.to_bits(), expected.to_bits(), "x = {x:e}");
        }
        for nan in [f32::NAN, f32::from_bits(0x7F80_0001), f32::from_bits(0xFF80_0001)] {
            assert!(Bf16::round_nearest(nan).load().is_nan());
            assert!(Bf16::round_stochastic(nan, 0xFFFF).load().is_nan());
        }
    }

    /// Over all 2¹⁶ random inputs the stochastic rounding's mean is `x` exactly: each
    /// neighbour is taken in proportion to `x`'s distance from the other.
    #[test]
    fn stochastic_rounding_is_exact_in_expectation() {
        for x in [1.0f32 + 1e-3, -0.999 * 7.3e-9, 2.0 - 1e-7, 1e-39, 123.456, 1.0] {
            let sum: f64 = (0..=0xFFFFu32)
                .map(|r| Bf16::round_stochastic(x, r).load() as f64)
                .sum();
            assert_eq!(sum / 65536.0, x as f64, "x = {x:e}");
            let (down, up) = neighbours(x.abs());
            for r in [0, 0x7FFF, 0xFFFF] {
                let y = Bf16::round_stochastic(x, r).load().abs();
                assert!(y == down || y == up, "x = {x:e}, r = {r}: {y:e}");
            }
        }
    }

    /// Without the NaN test, every value but NaN rounds as with it: zeros, subnormals,
    /// both ends of the range and infinities, and random bit patterns, at every kind of
    /// random bits.
    #[test]
    fn rounding_without_the_nan_test_is_the_same_but_for_nan() {
        let mut values = vec![
            0.0f32,
            -0.0,
            1e-45,
            -1e-45,
            f32::MIN_POSITIVE,
            f32::MAX,
            -f32::MAX,
        ];
        values.extend([f32::INFINITY, f32::NEG_INFINITY, Bf16::MAX, 1.0, -3.0078125]);
        let mut bits = 0x1234_5678u32;
        while values.len() < 200_000 {
            bits = bits.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let x = f32::from_bits(bits);
            if !x.is_nan() {
                values.push(x);
            }
        }
        for (i, &x) in values.iter().enumerate() {
            assert_eq!(Bf16::round_nearest_not_nan(x), Bf16::round_nearest(x), "{x:e}");
            for random in [0, 1, 0x7FFF, 0x8000, 0xFFFF, row_seed(i as u64, 3)] {
                assert_eq!(
                    Bf16::round_stochastic_not_nan(x, random),
                    Bf16::round_stochastic(x, random),
                    "{x:e}, {random:#x}"
                );
            }
        }
    }

    /// The tabulated bits are `channel_random`'s, bit for bit.
    #[test]
    fn channel_bits_are_channel_random() {
        let bits = ChannelBits::new(66);
        for row in (0..50_000u64).step_by(7) {
            for t in [1, 2, 9, 1000, i32::MAX] {
                let seed = row_seed(row, t);
                let row_part = ChannelBits::row_part(seed);
                for (ch, &part) in bits.parts().iter().enumerate() {
                    assert_eq!(ChannelBits::random(row_part, part), channel_random(seed, ch));
                }
            }
        }
    }

    /// The channels' random bits are spread evenly: their mean over many rows and steps
    /// is within 1 % of the midpoint, and no channel repeats its row neighbour's bits.
    #[test]
    fn channel_random_bits_are_uniform() {
        let mut sum = 0f64;
        let mut count = 0f64;
        let mut equal_neighbours = 0;
        for row in 0..2000u64 {
            for t in 1..8 {
                let seed = row_seed(row, t);
                for ch in 0..56 {
                    let r = channel_random(seed, ch);
                    assert!(r <= 0xFFFF);
                    sum += r as f64;
                    count += 1.0;
                    equal_neighbours += (r == channel_random(row_seed(row + 1, t), ch)) as u32;
                }
            }
        }
        let mean = sum / count / 65535.0;
        assert!((mean - 0.5).abs() < 0.01, "mean {mean}");
        assert!(
            equal_neighbours < 30,
            "{equal_neighbours} equal bits in neighbouring rows"
        );
    }
}
