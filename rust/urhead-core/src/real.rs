//! The float type kernels are generic over: `f32` for speed, `f64` for references,
//! finite differences and gradient checks.

use std::iter::Sum;
use std::ops::{AddAssign, MulAssign, SubAssign};

/// A float usable by every kernel. Implemented for `f32` and `f64`.
pub trait Real:
    num_traits::Float
    + num_traits::FloatConst
    + AddAssign
    + SubAssign
    + MulAssign
    + Sum
    + Send
    + Sync
    + Default
    + crate::memory::ZeroBits
    + std::fmt::Debug
    + 'static
{
    /// Lossy conversion from `f64`, for constants.
    fn c(x: f64) -> Self;
}

impl Real for f32 {
    #[inline(always)]
    fn c(x: f64) -> Self {
        x as f32
    }
}

impl Real for f64 {
    #[inline(always)]
    fn c(x: f64) -> Self {
        x
    }
}
