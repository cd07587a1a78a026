//! Tiny generic 3-vector / 3×3 helpers for per-joint and per-vertex math (row-major).

use crate::Real;

pub type V3<T> = [T; 3];
pub type M3<T> = [[T; 3]; 3];

/// `[f(0), f(1)]`, written out: `[0, 1].map(f)` goes through `core::array::try_map`,
/// which the inliner may leave out of line when code moves between codegen units
/// (measured twice: the splatting projection's backward 1.8–2.7 → 4.0–4.6 ms after
/// unrelated changes elsewhere in the crate).
#[inline(always)]
pub fn map2<U>(mut f: impl FnMut(usize) -> U) -> [U; 2] {
    [f(0), f(1)]
}

/// `[f(0), f(1), f(2)]`, written out (see [`map2`]).
#[inline(always)]
pub fn map3<U>(mut f: impl FnMut(usize) -> U) -> [U; 3] {
    [f(0), f(1), f(2)]
}

/// `[f(0), …, f(3)]`, written out (see [`map2`]).
#[inline(always)]
pub fn map4<U>(mut f: impl FnMut(usize) -> U) -> [U; 4] {
    [f(0), f(1), f(2), f(3)]
}

#[inline(always)]
pub fn zero3<T: Real>() -> M3<T> {
    [[T::zero(); 3]; 3]
}

#[inline(always)]
pub fn eye3<T: Real>() -> M3<T> {
    let mut m = zero3();
    for i in 0..3 {
        m[i][i] = T::one();
    }
    m
}

#[inline(always)]
pub fn matmul<T: Real>(a: &M3<T>, b: &M3<T>) -> M3<T> {
    let mut m = zero3();
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    m
}

/// aᵀ·b
#[inline(always)]
pub fn matmul_tn<T: Real>(a: &M3<T>, b: &M3<T>) -> M3<T> {
    matmul(&transpose(a), b)
}

/// a·bᵀ
#[inline(always)]
pub fn matmul_nt<T: Real>(a: &M3<T>, b: &M3<T>) -> M3<T> {
    matmul(a, &transpose(b))
}

#[inline(always)]
pub fn transpose<T: Real>(a: &M3<T>) -> M3<T> {
    map3(|i| [a[0][i], a[1][i], a[2][i]])
}

// matvec, matvec_t and outer are written out in full: `[0, 1, 2].map(..)` was once left
// out of line there too (rotate_normalize 4× slower, the closure called once per element).
#[inline(always)]
pub fn matvec<T: Real>(a: &M3<T>, v: &V3<T>) -> V3<T> {
    [dot(&a[0], v), dot(&a[1], v), dot(&a[2], v)]
}

#[inline(always)]
pub fn dot<T: Real>(a: &V3<T>, b: &V3<T>) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// aᵀ·v
#[inline(always)]
pub fn matvec_t<T: Real>(a: &M3<T>, v: &V3<T>) -> V3<T> {
    let column = |i: usize| dot(&[a[0][i], a[1][i], a[2][i]], v);
    [column(0), column(1), column(2)]
}

#[inline(always)]
pub fn add<T: Real>(a: &M3<T>, b: &M3<T>) -> M3<T> {
    map3(|i| map3(|j| a[i][j] + b[i][j]))
}

#[inline(always)]
pub fn scale<T: Real>(a: &M3<T>, s: T) -> M3<T> {
    map3(|i| map3(|j| a[i][j] * s))
}

/// Outer product a·bᵀ.
#[inline(always)]
pub fn outer<T: Real>(a: &V3<T>, b: &V3<T>) -> M3<T> {
    let row = |x: T| [x * b[0], x * b[1], x * b[2]];
    [row(a[0]), row(a[1]), row(a[2])]
}

/// Frobenius inner product Σ a∘b.
#[inline(always)]
pub fn frobenius<T: Real>(a: &M3<T>, b: &M3<T>) -> T {
    let mut s = T::zero();
    for i in 0..3 {
        for j in 0..3 {
            s += a[i][j] * b[i][j];
        }
    }
    s
}

/// The cross-product matrix: hat(w)·x = w × x.
#[inline(always)]
pub fn hat<T: Real>(w: &V3<T>) -> M3<T> {
    let z = T::zero();
    [[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]]
}
