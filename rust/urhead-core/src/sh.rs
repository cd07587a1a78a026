//! Real spherical harmonics of degree 0–3 with the 3DGS / gsplat constants and sign
//! convention, plus the 3DGS colour mapping `max(Σ b_k·c_k + 0.5, 0)`.

use crate::mat3::map3;
use crate::memory::Slot;
use crate::Real;

const C0: f64 = 0.282_094_791_773_878_14;
const C1: f64 = 0.488_602_511_902_919_9;
const C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Number of coefficients of a degree: (d + 1)².
pub const fn num_sh_coeffs(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

/// The basis values b_k(d) for k < (degree+1)² and their gradients ∂b_k/∂d (direction
/// components treated as independent, as in 3DGS).
#[inline]
pub fn sh_basis<T: Real>(degree: usize, d: [T; 3], with_grad: bool) -> ([T; 16], [[T; 3]; 16]) {
    let c = T::c;
    let [x, y, z] = d;
    let mut b = [T::zero(); 16];
    let mut g = [[T::zero(); 3]; 16];
    b[0] = c(C0);
    if degree >= 1 {
        b[1] = -c(C1) * y;
        b[2] = c(C1) * z;
        b[3] = -c(C1) * x;
        if with_grad {
            g[1] = [T::zero(), -c(C1), T::zero()];
            g[2] = [T::zero(), T::zero(), c(C1)];
            g[3] = [-c(C1), T::zero(), T::zero()];
        }
    }
    let (xx, yy, zz, xy, yz, xz) = (x * x, y * y, z * z, x * y, y * z, x * z);
    let two = c(2.0);
    if degree >= 2 {
        b[4] = c(C2[0]) * xy;
        b[5] = c(C2[1]) * yz;
        b[6] = c(C2[2]) * (two * zz - xx - yy);
        b[7] = c(C2[3]) * xz;
        b[8] = c(C2[4]) * (xx - yy);
        if with_grad {
            let z0 = T::zero();
            g[4] = [c(C2[0]) * y, c(C2[0]) * x, z0];
            g[5] = [z0, c(C2[1]) * z, c(C2[1]) * y];
            g[6] = [-two * c(C2[2]) * x, -two * c(C2[2]) * y, c(4.0) * c(C2[2]) * z];
            g[7] = [c(C2[3]) * z, z0, c(C2[3]) * x];
            g[8] = [two * c(C2[4]) * x, -two * c(C2[4]) * y, z0];
        }
    }
    if degree >= 3 {
        let (three, four) = (c(3.0), c(4.0));
        b[9] = c(C3[0]) * y * (three * xx - yy);
        b[10] = c(C3[1]) * xy * z;
        b[11] = c(C3[2]) * y * (four * zz - xx - yy);
        b[12] = c(C3[3]) * z * (two * zz - three * xx - three * yy);
        b[13] = c(C3[4]) * x * (four * zz - xx - yy);
        b[14] = c(C3[5]) * z * (xx - yy);
        b[15] = c(C3[6]) * x * (xx - three * yy);
        if with_grad {
            let z0 = T::zero();
            let (six, eight) = (c(6.0), c(8.0));
            g[9] = [six * c(C3[0]) * xy, three * c(C3[0]) * (xx - yy), z0];
            g[10] = [c(C3[1]) * yz, c(C3[1]) * xz, c(C3[1]) * xy];
            g[11] = [
                -two * c(C3[2]) * xy,
                c(C3[2]) * (four * zz - xx - three * yy),
                eight * c(C3[2]) * yz,
            ];
            g[12] = [
                -six * c(C3[3]) * xz,
                -six * c(C3[3]) * yz,
                c(C3[3]) * (six * zz - three * xx - three * yy),
            ];
            g[13] = [
                c(C3[4]) * (four * zz - three * xx - yy),
                -two * c(C3[4]) * xy,
                eight * c(C3[4]) * xz,
            ];
            g[14] = [two * c(C3[5]) * xz, -two * c(C3[5]) * yz, c(C3[5]) * (xx - yy)];
            g[15] = [three * c(C3[6]) * (xx - yy), -six * c(C3[6]) * xy, z0];
        }
    }
    (b, g)
}

/// Direction `i` of `(N, 3)` directions.
#[inline(always)]
pub fn direction<T: Real>(dirs: &[T], i: usize) -> [T; 3] {
    [dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]]
}

/// `start + Σ_k b_k·coeffs[3k + c]` per colour `c`, over the `coeffs.len() / 3`
/// coefficients given, in one fixed order: every SH colour in the crate is summed here, so a
/// fused op and the separate ones agree bit for bit. The even and the odd terms are summed
/// apart (`start` with the even ones), then added: two dependency chains of 8 instead of
/// one of 16, so a pixel's sum waits half as long (`sh_texture` forward −10 % in a frame,
/// −14 % in a training step).
#[inline(always)]
pub fn sh_sum<T: Real>(b: &[T; 16], coeffs: &[T], start: T) -> [T; 3] {
    let n = coeffs.len() / 3;
    let mut even = [start; 3];
    let mut odd = [T::zero(); 3];
    let mut k = 0;
    while k + 1 < n {
        for ch in 0..3 {
            even[ch] += b[k] * coeffs[k * 3 + ch];
            odd[ch] += b[k + 1] * coeffs[(k + 1) * 3 + ch];
        }
        k += 2;
    }
    if k < n {
        for ch in 0..3 {
            even[ch] += b[k] * coeffs[k * 3 + ch];
        }
    }
    map3(|ch| even[ch] + odd[ch])
}

/// `v_rgb` where the pre-clamp colour `raw` passed the clamp at 0 (`raw ≥ 0`), 0 elsewhere
/// (NaN included): the gradient the clamp lets through.
#[inline(always)]
pub fn unclamped<T: Real>(raw: [T; 3], v_rgb: [T; 3]) -> [T; 3] {
    map3(|ch| {
        if raw[ch] >= T::zero() {
            v_rgb[ch]
        } else {
            T::zero()
        }
    })
}

/// `dst[3k + c] = b_k·v[c]` for the `dst.len() / 3` coefficients: the coefficients'
/// gradient of [`sh_sum`] given the colour's `v`.
#[inline(always)]
pub fn sh_sum_adjoint<T: Real, O: Slot<T>>(b: &[T; 16], v: [T; 3], dst: &mut [O]) {
    for (k, row) in dst.chunks_exact_mut(3).enumerate() {
        for ch in 0..3 {
            row[ch].set(b[k] * v[ch]);
        }
    }
}

/// RGB = max(Σ_k b_k(dir)·coeffs[k] + 0.5, 0); `coeffs` is `(K, 3)` with K ≥ (degree+1)².
#[inline]
pub fn sh_to_rgb<T: Real>(degree: usize, dir: [T; 3], coeffs: &[T]) -> [T; 3] {
    let (b, _) = sh_basis(degree, dir, false);
    let rgb = sh_sum(&b, &coeffs[..3 * num_sh_coeffs(degree)], T::c(0.5));
    rgb.map(|v| if v >= T::zero() { v } else { T::zero() })
}

/// Adjoint of [`sh_to_rgb`]: adds ∂L/∂coeffs into `v_coeffs` (if given) and returns
/// ∂L/∂dir. Channels clamped at 0 pass no gradient.
#[inline]
pub fn sh_to_rgb_backward<T: Real>(
    degree: usize,
    dir: [T; 3],
    coeffs: &[T],
    v_rgb: [T; 3],
    v_coeffs: Option<&mut [T]>,
) -> [T; 3] {
    let (b, g) = sh_basis(degree, dir, true);
    let n = num_sh_coeffs(degree);
    let v = unclamped(sh_sum(&b, &coeffs[..3 * n], T::c(0.5)), v_rgb);
    if let Some(vc) = v_coeffs {
        for k in 0..n {
            for ch in 0..3 {
                vc[k * 3 + ch] += b[k] * v[ch];
            }
        }
    }
    let mut v_dir = [T::zero(); 3];
    for k in 1..n {
        let s = coeffs[k * 3] * v[0] + coeffs[k * 3 + 1] * v[1] + coeffs[k * 3 + 2] * v[2];
        for a in 0..3 {
            v_dir[a] += g[k][a] * s;
        }
    }
    v_dir
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;

    #[test]
    fn basis_gradient_matches_finite_differences() {
        let mut rng = Rng::new(2);
        for _ in 0..20 {
            let d: [f64; 3] = std::array::from_fn(|_| rng.uniform(-1.0, 1.0));
            let (_, g) = sh_basis(3, d, true);
            for a in 0..3 {
                let h = 1e-6;
                let mut dp = d;
                let mut dm = d;
                dp[a] += h;
                dm[a] -= h;
                let (bp, _) = sh_basis(3, dp, false);
                let (bm, _) = sh_basis(3, dm, false);
                for k in 0..16 {
                    let fd = (bp[k] - bm[k]) / (2.0 * h);
                    assert!((fd - g[k][a]).abs() < 1e-8, "k {k} axis {a}: {fd} vs {}", g[k][a]);
                }
            }
        }
    }

    #[test]
    fn degree_zero_is_dc_plus_half() {
        let rgb = sh_to_rgb(0, [0.0f64, 0.0, 1.0], &[1.0, -10.0, 0.0]);
        assert_eq!(rgb, [C0 + 0.5, 0.0, 0.5]);
    }
}
