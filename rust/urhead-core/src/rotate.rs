//! `normalise(R·v)` (or `normalise(Rᵀ·v)`) for many 3×3 matrices and vectors, forward and
//! adjoint: posing the avatar's rest-frame normals (vertices and covered pixels, gradients to
//! both the skinning rotations and the normals) and taking camera rays back to the rest frame
//! (constants). torch's `bmm` is slow on batches of 3×3 matrices, its backward more so; here
//! one pass over the rows does the product, the normalisation and their adjoints.
//!
//! `normalise` divides by `max(|m|, 1e-12)`, as `m / m.norm().clamp_min(1e-12)` does: a zero
//! vector stays zero, and below the floor the gradient is that of `m / 1e-12`. `|m|` is
//! computed without overflow (huge vectors are normalised, where the plain sum of squares
//! would give inf and a zero vector). Non-finite values are data, not errors: a row whose
//! product holds NaN or ±inf gives NaN in its output and NaN gradients to its inputs, as the
//! torch expression does (even for a zero upstream gradient); other rows are unaffected.

use rayon::prelude::*;

use crate::error::{check_indices, check_len, Error, Result};
use crate::mat3::{dot, matvec, matvec_t, outer, M3, V3};
use crate::memory::{assume_written, copy_short, unwritten};
use crate::parallel::optional_chunks;
use crate::Real;

/// Rows per rayon task; fixed, so the partition does not depend on the thread count (each
/// row is independent anyway).
const CHUNK: usize = 2048;
/// `normalise` divides by `max(|v|, NORM_FLOOR)`, as `v / v.norm().clamp_min(1e-12)`.
pub const NORM_FLOOR: f64 = 1e-12;

/// The arguments shared by the forward and the backward (row-major, contiguous).
#[derive(Clone, Copy)]
pub struct RotateInputs<'a, T> {
    /// (N, 3, 3) matrices; rotations in practice, but any matrix is valid.
    pub rotations: &'a [T],
    /// (N, 3) vectors, any length (zero and non-finite allowed); with `rows`, an (M, 3)
    /// table the rows pick from.
    pub vectors: &'a [T],
    /// Apply `Rᵀ` instead of `R`.
    pub transpose: bool,
    /// (N,) indices into `vectors`: row i uses `vectors[rows[i]]`, gathered as it is read
    /// (a mesh's covered pixels pick their camera rays from the whole image's table with no
    /// (N, 3) copy). The gathered vectors get no gradient.
    pub rows: Option<&'a [i64]>,
}

/// Which input gradients [`rotate_normalize_backward`] computes.
#[derive(Debug, Clone, Copy)]
pub struct RotateNeeds {
    pub rotations: bool,
    pub vectors: bool,
}

/// The input gradients, `None` where not requested.
#[derive(Debug, Clone)]
pub struct RotateGrads<T> {
    /// (N, 3, 3)
    pub v_rotations: Option<Vec<T>>,
    /// (N, 3)
    pub v_vectors: Option<Vec<T>>,
}

impl<T: Real> RotateInputs<'_, T> {
    /// Checks the lengths and the rows; returns N.
    fn validate(&self) -> Result<usize> {
        let table = self.vectors.len() / 3;
        let layout = if self.rows.is_some() { "(M, 3)" } else { "(N, 3)" };
        check_len("vectors", self.vectors, table * 3, layout)?;
        let n = match self.rows {
            None => table,
            Some(rows) => {
                check_indices("rows", rows, 0, table as i64)?;
                rows.len()
            }
        };
        check_len(
            "rotations",
            self.rotations,
            n * 9,
            &format!("(N, 3, 3) with N = {n} like vectors"),
        )?;
        Ok(n)
    }

    #[inline(always)]
    fn matrix(&self, i: usize) -> M3<T> {
        let r = &self.rotations[9 * i..9 * i + 9];
        [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]]
    }

    #[inline(always)]
    fn vector(&self, i: usize) -> V3<T> {
        let k = self.rows.map_or(i, |rows| rows[i] as usize);
        [
            self.vectors[3 * k],
            self.vectors[3 * k + 1],
            self.vectors[3 * k + 2],
        ]
    }

    /// `R·v`, or `Rᵀ·v` with `transpose`.
    #[inline(always)]
    fn rotated(&self, matrix: &M3<T>, vector: &V3<T>) -> V3<T> {
        if self.transpose {
            matvec_t(matrix, vector)
        } else {
            matvec(matrix, vector)
        }
    }
}

/// |v|, without overflow: when the plain sum of squares overflows (|v| ≳ 1.8e19 in f32),
/// scaled by the largest component. NaN for NaN, +inf for an infinite component.
#[inline(always)]
fn length<T: Real>(v: &V3<T>) -> T {
    let sq = dot(v, v);
    if sq.is_finite() || sq.is_nan() {
        return sq.sqrt();
    }
    let peak = v[0].abs().max(v[1].abs()).max(v[2].abs());
    if !peak.is_finite() {
        return peak;
    }
    let s = v.map(|x| x / peak);
    peak * dot(&s, &s).sqrt()
}

/// `(v / max(|v|, 1e-12), |v|)`: zero stays zero, NaN stays NaN.
#[inline(always)]
pub(crate) fn normalise<T: Real>(v: V3<T>) -> (V3<T>, T) {
    let len = length(&v);
    let floor = T::c(NORM_FLOOR);
    // NaN-safe: a NaN length divides by NaN, as the reference does.
    let div = if len < floor { floor } else { len };
    ([v[0] / div, v[1] / div, v[2] / div], len)
}

/// Adjoint of [`normalise`] at `v` with output `n` and length `len`: through the length
/// where `len ≥ 1e-12` (where the clamp passes gradient), through `v / 1e-12` below.
#[inline(always)]
pub(crate) fn normalise_backward<T: Real>(n: &V3<T>, len: T, v_n: &V3<T>) -> V3<T> {
    let floor = T::c(NORM_FLOOR);
    if len < floor {
        return [v_n[0] / floor, v_n[1] / floor, v_n[2] / floor];
    }
    let along = dot(n, v_n);
    let project = |c: usize| (v_n[c] - n[c] * along) / len;
    [project(0), project(1), project(2)]
}

/// (N, 3) unit `R·v` (`Rᵀ·v` with `transpose`), zero for a zero product.
pub fn rotate_normalize_forward<T: Real>(inputs: &RotateInputs<'_, T>) -> Result<Vec<T>> {
    let n = inputs.validate()?;
    let mut out = unwritten("rotate_normalize output", n * 3)?;
    out.par_chunks_mut(CHUNK * 3).enumerate().for_each(|(c, block)| {
        for (j, unit) in block.chunks_exact_mut(3).enumerate() {
            let i = c * CHUNK + j;
            let rotated = inputs.rotated(&inputs.matrix(i), &inputs.vector(i));
            copy_short(unit, &normalise(rotated).0, 3);
        }
    });
    // SAFETY: the blocks partition the rows, and each row was written whole.
    Ok(unsafe { assume_written(out) })
}

/// The adjoint of [`rotate_normalize_forward`] from ∂L/∂output (N, 3), computing only the
/// gradients flagged in `needs`. With `m = R·v` and `g = ∂L/∂m`: `∂L/∂R = g ⊗ v`,
/// `∂L/∂v = Rᵀ·g` (transposed: `m = Rᵀ·v`, `∂L/∂R = v ⊗ g`, `∂L/∂v = R·g`).
pub fn rotate_normalize_backward<T: Real>(
    inputs: &RotateInputs<'_, T>,
    v_out: &[T],
    needs: &RotateNeeds,
) -> Result<RotateGrads<T>> {
    let n = inputs.validate()?;
    check_len("v_out", v_out, n * 3, &format!("(N, 3) with N = {n}"))?;
    if needs.vectors && inputs.rows.is_some() {
        return Err(Error::Invalid {
            arg: "needs",
            reason: "gathered vectors (rows given) get no gradient".into(),
        });
    }
    let size = |needed: bool, width: usize| if needed { n * width } else { 0 };
    // Written whole, row by row, below (when asked for; empty otherwise).
    let mut v_rotations = unwritten("rotate_normalize rotation gradient", size(needs.rotations, 9))?;
    let mut v_vectors = unwritten("rotate_normalize vector gradient", size(needs.vectors, 3))?;
    let tasks = n.div_ceil(CHUNK);
    let rotation_chunks = optional_chunks(
        needs.rotations.then_some(v_rotations.as_mut_slice()),
        CHUNK * 9,
        tasks,
    );
    let vector_chunks = optional_chunks(
        needs.vectors.then_some(v_vectors.as_mut_slice()),
        CHUNK * 3,
        tasks,
    );
    rotation_chunks
        .into_par_iter()
        .zip(vector_chunks)
        .enumerate()
        .for_each(|(c, (mut dr, mut dv))| {
            let rows = (n - c * CHUNK).min(CHUNK);
            for j in 0..rows {
                let i = c * CHUNK + j;
                let (matrix, vector) = (inputs.matrix(i), inputs.vector(i));
                let (unit, len) = normalise(inputs.rotated(&matrix, &vector));
                let v_unit = [v_out[3 * i], v_out[3 * i + 1], v_out[3 * i + 2]];
                let g = normalise_backward(&unit, len, &v_unit);
                if let Some(dr) = dr.as_deref_mut() {
                    let v_r = if inputs.transpose {
                        outer(&vector, &g)
                    } else {
                        outer(&g, &vector)
                    };
                    for (dst, src) in dr[9 * j..9 * j + 9].iter_mut().zip(v_r.iter().flatten()) {
                        dst.write(*src);
                    }
                }
                if let Some(dv) = dv.as_deref_mut() {
                    let v_v = if inputs.transpose {
                        matvec(&matrix, &g)
                    } else {
                        matvec_t(&matrix, &g)
                    };
                    copy_short(&mut dv[3 * j..], &v_v, 3);
                }
            }
        });
    // SAFETY: the chunks partition the rows, and every row of an asked-for gradient was
    // written whole (9 and 3 values); one not asked for is empty.
    let (v_rotations, v_vectors) = unsafe { (assume_written(v_rotations), assume_written(v_vectors)) };
    Ok(RotateGrads {
        v_rotations: needs.rotations.then_some(v_rotations),
        v_vectors: needs.vectors.then_some(v_vectors),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{on_threads, Rng};

    struct Case<T> {
        rotations: Vec<T>,
        vectors: Vec<T>,
    }

    impl<T: Real> Case<T> {
        /// Near-rotations (identity plus a perturbation: not orthogonal) and vectors.
        fn new(n: usize, seed: u64) -> Self {
            let mut rng = Rng::new(seed);
            let mut rotations = Vec::with_capacity(n * 9);
            for _ in 0..n {
                for r in 0..3 {
                    for c in 0..3 {
                        let eye = if r == c { 1.0 } else { 0.0 };
                        rotations.push(T::c(eye + rng.uniform(-0.3, 0.3)));
                    }
                }
            }
            Self {
                rotations,
                vectors: rng.vec(n * 3, -1.0, 1.0),
            }
        }

        fn inputs(&self, transpose: bool) -> RotateInputs<'_, T> {
            RotateInputs {
                rotations: &self.rotations,
                vectors: &self.vectors,
                transpose,
                rows: None,
            }
        }
    }

    const BOTH: RotateNeeds = RotateNeeds {
        rotations: true,
        vectors: true,
    };

    #[test]
    fn forward_follows_the_definition() {
        let case = Case::<f64>::new(50, 1);
        for transpose in [false, true] {
            let out = rotate_normalize_forward(&case.inputs(transpose)).unwrap();
            for i in 0..50 {
                let r = &case.rotations[9 * i..9 * i + 9];
                let v = &case.vectors[3 * i..3 * i + 3];
                let m: Vec<f64> = (0..3)
                    .map(|k| {
                        (0..3)
                            .map(|l| if transpose { r[3 * l + k] } else { r[3 * k + l] } * v[l])
                            .sum()
                    })
                    .collect();
                let len = m.iter().map(|x| x * x).sum::<f64>().sqrt();
                for k in 0..3 {
                    assert!((out[3 * i + k] - m[k] / len).abs() < 1e-15);
                }
            }
        }
    }

    fn loss(case: &Case<f64>, transpose: bool, w: &[f64]) -> f64 {
        let out = rotate_normalize_forward(&case.inputs(transpose)).unwrap();
        out.iter().zip(w).map(|(a, b)| a * b).sum()
    }

    #[test]
    fn backward_matches_central_differences() {
        let n = 40;
        let mut case = Case::<f64>::new(n, 2);
        // One product below the floor: its gradient is that of m / 1e-12.
        case.vectors[3..6].copy_from_slice(&[1e-14, -2e-14, 5e-15]);
        let mut rng = Rng::new(5);
        let w: Vec<f64> = rng.vec(n * 3, -1.0, 1.0);
        for transpose in [false, true] {
            let g = rotate_normalize_backward(&case.inputs(transpose), &w, &BOTH).unwrap();
            type Field = fn(&mut Case<f64>) -> &mut Vec<f64>;
            let fields: [(&str, Field, &Vec<f64>); 2] = [
                ("rotations", |c| &mut c.rotations, g.v_rotations.as_ref().unwrap()),
                ("vectors", |c| &mut c.vectors, g.v_vectors.as_ref().unwrap()),
            ];
            for (name, field, grad) in fields {
                // Steps relative to each entry, so the tiny row is probed at its own scale.
                let base = field(&mut clone(&case)).clone();
                for trial in 0..4 {
                    let step: Vec<f64> = base
                        .iter()
                        .map(|x| 1e-6 * x.abs() * rng.uniform(-1.0, 1.0))
                        .collect();
                    let (mut plus, mut minus) = (clone(&case), clone(&case));
                    for (k, s) in step.iter().enumerate() {
                        field(&mut plus)[k] += s;
                        field(&mut minus)[k] -= s;
                    }
                    let fd = (loss(&plus, transpose, &w) - loss(&minus, transpose, &w)) / 2.0;
                    let analytic: f64 = grad.iter().zip(&step).map(|(a, b)| a * b).sum();
                    let err = (fd - analytic).abs() / analytic.abs().max(1e-6);
                    assert!(
                        err < 1e-7,
                        "{name} transpose {transpose} trial {trial}: fd {fd} vs {analytic}"
                    );
                }
            }
        }
    }

    fn clone(c: &Case<f64>) -> Case<f64> {
        Case {
            rotations: c.rotations.clone(),
            vectors: c.vectors.clone(),
        }
    }

    #[test]
    fn skipped_gradients_are_none_and_the_others_unchanged() {
        let case = Case::<f32>::new(3000, 3);
        let w: Vec<f32> = Rng::new(4).vec(3000 * 3, -1.0, 1.0);
        let both = rotate_normalize_backward(&case.inputs(false), &w, &BOTH).unwrap();
        let only = |rotations, vectors| {
            let needs = RotateNeeds { rotations, vectors };
            rotate_normalize_backward(&case.inputs(false), &w, &needs).unwrap()
        };
        let r = only(true, false);
        assert_eq!(r.v_rotations, both.v_rotations);
        assert!(r.v_vectors.is_none());
        let v = only(false, true);
        assert_eq!(v.v_vectors, both.v_vectors);
        assert!(v.v_rotations.is_none());
        let none = only(false, false);
        assert!(none.v_rotations.is_none() && none.v_vectors.is_none());
    }

    #[test]
    fn zero_tiny_huge_and_non_finite_vectors() {
        let rows: [[f32; 3]; 6] = [
            [0.0; 3],
            [1e-30, 0.0, -1e-30],
            [1e30, -2e30, 5e29],
            [f32::NAN, 0.0, 1.0],
            [f32::INFINITY, 0.0, 0.0],
            [0.6, 0.0, 0.8],
        ];
        let eye: Vec<f32> = (0..6)
            .flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
            .collect();
        let vectors: Vec<f32> = rows.iter().flatten().copied().collect();
        let inputs = RotateInputs {
            rotations: &eye,
            vectors: &vectors,
            transpose: false,
            rows: None,
        };
        let out = rotate_normalize_forward(&inputs).unwrap();
        assert_eq!(&out[0..3], &[0.0; 3]);
        // Below the floor: divided by 1e-12, not normalised.
        assert_eq!(&out[3..6], &[1e-30f32 / 1e-12f32, 0.0, -1e-30f32 / 1e-12f32]);
        // Huge: normalised, not overflowed to zero.
        let huge = &out[6..9];
        assert!((huge.iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-6);
        // NaN in, NaN out; inf meets the matrix's zeros (0·inf = NaN), as in `bmm`.
        assert!(out[9..15].iter().all(|x| x.is_nan()));
        assert_eq!(&out[15..18], &[0.6, 0.0, 0.8]);
        let w = vec![0.0f32; 18];
        let g = rotate_normalize_backward(&inputs, &w, &BOTH).unwrap();
        let (dr, dv) = (g.v_rotations.unwrap(), g.v_vectors.unwrap());
        // NaN rows give NaN gradients even for a zero upstream gradient (as torch does);
        // the finite rows give exact zeros.
        for (row, finite) in [true, true, true, false, false, true].into_iter().enumerate() {
            let (r, v) = (&dr[9 * row..9 * row + 9], &dv[3 * row..3 * row + 3]);
            if finite {
                assert!(r.iter().chain(v).all(|x| *x == 0.0), "row {row}");
            } else {
                assert!(r.iter().chain(v).all(|x| x.is_nan()), "row {row}");
            }
        }
        // The zero vector's gradient is that of m / 1e-12.
        let mut w = vec![0.0f32; 18];
        w[0..3].copy_from_slice(&[1.0, -2.0, 3.0]);
        let dv = rotate_normalize_backward(&inputs, &w, &BOTH)
            .unwrap()
            .v_vectors
            .unwrap();
        assert_eq!(&dv[0..3], &[1.0, -2.0, 3.0].map(|x: f32| x / 1e-12f32));
    }

    #[test]
    fn gathered_rows_are_the_gathered_vectors_bit_for_bit() {
        let n = 5000; // several chunks
        let case = Case::<f32>::new(n, 9);
        let mut rng = Rng::new(10);
        // A table larger than N, picked in increasing order with gaps and repeats, as a
        // mesh's covered pixels pick their rays.
        let table: Vec<f32> = rng.vec(3 * 3 * n, -1.0, 1.0);
        let mut rows: Vec<i64> = (0..n).map(|_| rng.uniform(0.0, (3 * n) as f64) as i64).collect();
        rows.sort_unstable();
        rows[1] = rows[0];
        let picked: Vec<f32> = rows
            .iter()
            .flat_map(|&r| table[3 * r as usize..3 * r as usize + 3].to_vec())
            .collect();
        let w: Vec<f32> = rng.vec(n * 3, -1.0, 1.0);
        let only_rotations = RotateNeeds {
            rotations: true,
            vectors: false,
        };
        for transpose in [false, true] {
            let copied = RotateInputs {
                vectors: &picked,
                ..case.inputs(transpose)
            };
            let gathered = RotateInputs {
                vectors: &table,
                rows: Some(&rows),
                ..case.inputs(transpose)
            };
            let bits = |x: &[f32]| x.iter().map(|y| y.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                bits(&rotate_normalize_forward(&copied).unwrap()),
                bits(&rotate_normalize_forward(&gathered).unwrap())
            );
            let g_copied = rotate_normalize_backward(&copied, &w, &only_rotations).unwrap();
            let g_gathered = rotate_normalize_backward(&gathered, &w, &only_rotations).unwrap();
            assert_eq!(
                bits(g_copied.v_rotations.as_ref().unwrap()),
                bits(g_gathered.v_rotations.as_ref().unwrap())
            );
            assert!(g_gathered.v_vectors.is_none());
            // The gathered vectors get no gradient: asking for one is an error.
            let err = rotate_normalize_backward(&gathered, &w, &BOTH).unwrap_err();
            assert!(matches!(err, Error::Invalid { arg: "needs", .. }), "{err}");
        }
        // A row outside the table is named, as is a row count unlike the rotations'.
        let mut bad = rows.clone();
        bad[7] = 3 * n as i64;
        let outside = RotateInputs {
            vectors: &table,
            rows: Some(&bad),
            ..case.inputs(false)
        };
        let err = rotate_normalize_forward(&outside).unwrap_err();
        assert!(
            matches!(
                err,
                Error::IndexOutOfRange {
                    arg: "rows",
                    index: 7,
                    ..
                }
            ),
            "{err}"
        );
        let short = RotateInputs {
            vectors: &table,
            rows: Some(&rows[1..]),
            ..case.inputs(false)
        };
        let err = rotate_normalize_forward(&short).unwrap_err();
        assert!(matches!(err, Error::Shape { arg: "rotations", .. }), "{err}");
    }

    #[test]
    fn same_bits_for_any_thread_count() {
        let n = 9000; // several chunks and a partial one
        let case = Case::<f32>::new(n, 6);
        let w: Vec<f32> = Rng::new(7).vec(n * 3, -1.0, 1.0);
        let run = |threads: usize, transpose: bool| {
            on_threads(threads, || {
                let inputs = case.inputs(transpose);
                let out = rotate_normalize_forward(&inputs).unwrap();
                let g = rotate_normalize_backward(&inputs, &w, &BOTH).unwrap();
                let bits = |x: &[f32]| x.iter().map(|y| y.to_bits()).collect::<Vec<_>>();
                [
                    bits(&out),
                    bits(g.v_rotations.as_ref().unwrap()),
                    bits(g.v_vectors.as_ref().unwrap()),
                ]
            })
        };
        for transpose in [false, true] {
            let one = run(1, transpose);
            for threads in [2, 3] {
                assert!(one == run(threads, transpose), "{threads} threads differ from 1");
            }
        }
    }

    #[test]
    fn rejects_bad_arguments() {
        let case = Case::<f32>::new(4, 8);
        let ok = case.inputs(false);
        assert!(rotate_normalize_forward(&ok).is_ok());
        let shape = |arg: &str, e: Error| matches!(e, Error::Shape { arg: a, .. } if a == arg);
        let short_rotations = RotateInputs {
            rotations: &case.rotations[9..],
            ..ok
        };
        assert!(shape(
            "rotations",
            rotate_normalize_forward(&short_rotations).unwrap_err()
        ));
        let ragged = RotateInputs {
            vectors: &case.vectors[1..],
            ..ok
        };
        assert!(shape("vectors", rotate_normalize_forward(&ragged).unwrap_err()));
        assert!(shape(
            "v_out",
            rotate_normalize_backward(&ok, &[0.0; 11], &BOTH).unwrap_err()
        ));
        // No rows: empty outputs.
        let empty = RotateInputs::<f32> {
            rotations: &[],
            vectors: &[],
            transpose: true,
            rows: None,
        };
        assert!(rotate_normalize_forward(&empty).unwrap().is_empty());
        let g = rotate_normalize_backward(&empty, &[], &BOTH).unwrap();
        assert!(g.v_rotations.unwrap().is_empty() && g.v_vectors.unwrap().is_empty());
    }
}
