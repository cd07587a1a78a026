//! Axis-angle → rotation matrix, stable at every angle.
//!
//! R = I + a(θ)·K + b(θ)·K² with K = hat(ω), θ = |ω|, a = sin θ / θ, b = (1 − cos θ)/θ².
//! The scalar coefficients are evaluated in f64 whatever `T` is (in f32, 1 − cos θ is
//! exactly 0 for θ < 2.4e-4) and through their Taylor series below θ = 1e-2, so R keeps its
//! second-order term and the derivative at θ = 0 is exactly the generator hat(e_k).

use crate::mat3::{add, eye3, hat, map3, matmul, scale, M3, V3};
use crate::Real;

/// Below this angle the coefficients come from their Taylor series.
const TAYLOR_BELOW: f64 = 1e-2;

/// a = sin θ/θ, b = (1 − cos θ)/θ², and their derivatives divided by θ:
/// da = a'(θ)/θ, db = b'(θ)/θ (so ∂a/∂ω_k = da·ω_k).
struct Coefficients {
    a: f64,
    b: f64,
    da: f64,
    db: f64,
}

fn coefficients(theta_sq: f64) -> Coefficients {
    let t2 = theta_sq;
    if t2 < TAYLOR_BELOW * TAYLOR_BELOW {
        let t4 = t2 * t2;
        Coefficients {
            a: 1.0 - t2 / 6.0 + t4 / 120.0,
            b: 0.5 - t2 / 24.0 + t4 / 720.0,
            da: -1.0 / 3.0 + t2 / 30.0 - t4 / 840.0,
            db: -1.0 / 12.0 + t2 / 180.0 - t4 / 6720.0,
        }
    } else {
        let t = t2.sqrt();
        let (s, c) = t.sin_cos();
        Coefficients {
            a: s / t,
            b: (1.0 - c) / t2,
            da: (t * c - s) / (t2 * t),
            db: (t * s - 2.0 * (1.0 - c)) / (t2 * t2),
        }
    }
}

fn theta_sq<T: Real>(w: &V3<T>) -> f64 {
    w.iter().map(|x| x.to_f64().unwrap_or(f64::NAN).powi(2)).sum()
}

/// Rotation matrix of the axis-angle vector `w`.
pub fn rotation<T: Real>(w: &V3<T>) -> M3<T> {
    let co = coefficients(theta_sq(w));
    let k = hat(w);
    add(
        &add(&eye3(), &scale(&k, T::c(co.a))),
        &scale(&matmul(&k, &k), T::c(co.b)),
    )
}

/// Rotation matrix and its three partial derivatives ∂R/∂ω_k.
pub fn rotation_with_jacobian<T: Real>(w: &V3<T>) -> (M3<T>, [M3<T>; 3]) {
    let co = coefficients(theta_sq(w));
    let k = hat(w);
    let k2 = matmul(&k, &k);
    let (a, b) = (T::c(co.a), T::c(co.b));
    let r = add(&add(&eye3(), &scale(&k, a)), &scale(&k2, b));
    let jac = map3(|i| {
        let mut e = [T::zero(); 3];
        e[i] = T::one();
        let g = hat(&e);
        // ∂(a K)/∂ω_i = da ω_i K + a G_i; ∂(b K²)/∂ω_i = db ω_i K² + b (G_i K + K G_i)
        let d_a = add(&scale(&k, T::c(co.da) * w[i]), &scale(&g, a));
        let d_b = add(
            &scale(&k2, T::c(co.db) * w[i]),
            &scale(&add(&matmul(&g, &k), &matmul(&k, &g)), b),
        );
        add(&d_a, &d_b)
    });
    (r, jac)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mat3::{matmul_tn, transpose};

    fn max_abs_diff(a: &M3<f64>, b: &M3<f64>) -> f64 {
        let mut m: f64 = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                m = m.max((a[i][j] - b[i][j]).abs());
            }
        }
        m
    }

    #[test]
    fn orthonormal_across_angles() {
        for &t in &[
            0.0,
            1e-12,
            1e-8,
            1e-4,
            2.4e-4,
            1e-2,
            1.0,
            3.0,
            std::f64::consts::PI,
            10.0 * std::f64::consts::PI,
        ] {
            let w = [t * 0.6, -t * 0.48, t * 0.64];
            let r = rotation(&w);
            assert!(max_abs_diff(&matmul_tn(&r, &r), &eye3()) < 1e-12, "theta {t}");
        }
    }

    #[test]
    fn generator_at_zero() {
        let (r, jac) = rotation_with_jacobian(&[0.0f64; 3]);
        assert_eq!(r, eye3());
        for i in 0..3 {
            let mut e = [0.0; 3];
            e[i] = 1.0;
            assert_eq!(jac[i], hat(&e));
        }
    }

    #[test]
    fn jacobian_matches_central_differences() {
        for &t in &[1e-3, 9.9e-3, 1.01e-2, 0.5, 2.0, std::f64::consts::PI - 1e-6, 7.0] {
            let w = [t * 0.36, t * 0.48, -t * 0.8];
            let (_, jac) = rotation_with_jacobian(&w);
            for i in 0..3 {
                let h = 1e-6;
                let (mut wp, mut wm) = (w, w);
                wp[i] += h;
                wm[i] -= h;
                let fd = scale(&add(&rotation(&wp), &scale(&rotation(&wm), -1.0)), 0.5 / h);
                assert!(max_abs_diff(&fd, &jac[i]) < 1e-7, "theta {t} axis {i}");
            }
        }
    }

    #[test]
    fn second_order_term_kept_below_f32_cosine_resolution() {
        // 1 - cos(1e-4) rounds to 0 in f32; the Taylor path must keep the K²/2 term.
        let r = rotation(&[1e-4f64, 0.0, 0.0]);
        assert!((r[1][1] - 1.0 + 0.5e-8).abs() < 1e-15);
        assert!((r[2][1] - 1e-4 * (1.0 - 1e-8 / 6.0)).abs() < 1e-20);
        assert_eq!(transpose(&r)[1][2], r[2][1]);
    }
}
