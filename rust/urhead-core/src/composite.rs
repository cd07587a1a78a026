//! `composite`: a premultiplied image in front over one behind, `out = front + T·back` per
//! pixel and colour channel (`T` the front's transmittance), forward and adjoint: the
//! avatar's Gaussians over its antialiased mesh. As torch elementwise ops (a broadcast
//! product, a sum, and a channel reduction in the backward) it costs ~7 ms a 512² training
//! step; here each pass is one walk over the pixels.
//!
//! `back` may hold more channels than the three it contributes (the mesh's colour and
//! coverage, `(P, S)` with `S ≥ 3`), so a view of the colour needs no copy; its gradient
//! has the same layout, zero past the colour. Non-finite values are data (NaN in, NaN out).
//! Every pixel is independent: the same bits for any thread count.

use rayon::prelude::*;

use crate::error::{check_len, Error, Result};
use crate::memory::{assume_written, unwritten, zeroed};
use crate::parallel::optional_chunks;
use crate::Real;

/// Pixels per rayon task (fixed, so the partition does not depend on the thread count).
const CHUNK: usize = 4096;

/// The arguments shared by the forward and the backward (row-major, contiguous).
#[derive(Debug, Clone, Copy)]
pub struct CompositeInputs<'a, T> {
    /// `(P, 3)` premultiplied colour in front.
    pub front: &'a [T],
    /// `(P,)` the front's transmittance.
    pub transmittance: &'a [T],
    /// `(P, S)`, colour in the first three channels.
    pub back: &'a [T],
    /// `S ≥ 3`.
    pub back_channels: usize,
}

/// The gradients of [`composite_backward`], `None` where not asked for (the front's is the
/// output's own).
#[derive(Debug, Clone)]
pub struct CompositeGrads<T> {
    /// `(P,)`
    pub v_transmittance: Option<Vec<T>>,
    /// `(P, S)`, zero past the colour.
    pub v_back: Option<Vec<T>>,
}

impl<T: Real> CompositeInputs<'_, T> {
    /// Checks the lengths; returns P.
    fn validate(&self) -> Result<usize> {
        let s = self.back_channels;
        if s < 3 {
            return Err(Error::Invalid {
                arg: "back",
                reason: format!("needs at least 3 channels (colour first), got {s}"),
            });
        }
        let p = self.transmittance.len();
        check_len("front", self.front, 3 * p, &format!("(P, 3) = ({p}, 3)"))?;
        check_len("back", self.back, s * p, &format!("(P, S) = ({p}, {s})"))?;
        Ok(p)
    }
}

/// `(P, 3)`: `front + T·back[:, :3]`.
pub fn composite_forward<T: Real>(inputs: &CompositeInputs<'_, T>) -> Result<Vec<T>> {
    let p = inputs.validate()?;
    let s = inputs.back_channels;
    let mut out = unwritten("composite (P, 3)", 3 * p)?;
    out.par_chunks_mut(3 * CHUNK)
        .enumerate()
        .for_each(|(chunk, out)| {
            let first = chunk * CHUNK;
            for (i, o) in out.chunks_exact_mut(3).enumerate() {
                let px = first + i;
                let t = inputs.transmittance[px];
                let (front, back) = (
                    &inputs.front[3 * px..3 * px + 3],
                    &inputs.back[s * px..s * px + 3],
                );
                for c in 0..3 {
                    o[c].write(front[c] + t * back[c]);
                }
            }
        });
    // SAFETY: the chunks partition the pixels, and each pixel's 3 values were written.
    Ok(unsafe { assume_written(out) })
}

/// The adjoint of [`composite_forward`] given `v_out (P, 3)`: `v_T = Σ_c v_out·back`,
/// `v_back = T·v_out` (zero past the colour).
pub fn composite_backward<T: Real>(
    inputs: &CompositeInputs<'_, T>,
    v_out: &[T],
    need_transmittance: bool,
    need_back: bool,
) -> Result<CompositeGrads<T>> {
    let p = inputs.validate()?;
    check_len("v_out", v_out, 3 * p, &format!("(P, 3) = ({p}, 3)"))?;
    behind_gradients(
        inputs.transmittance,
        inputs.back,
        inputs.back_channels,
        v_out,
        3,
        None,
        need_transmittance,
        need_back,
    )
}

/// The gradients of what lies behind a premultiplied `C`-channel front, `front + T·back`,
/// given `v_out (P, C)` (lengths checked by the caller): `v_T = Σ_c v_out·back (+ v_T_in)`
/// and `v_back = T·v_out` on `back`'s first C of `S` channels, zero past them; `None`
/// where not asked for. One streaming pass, shared by [`composite_backward`] and the
/// splatting backward over an image background (whose `v_T_in` is the transmittance's own
/// upstream gradient).
#[allow(clippy::too_many_arguments)]
pub(crate) fn behind_gradients<T: Real>(
    transmittance: &[T],
    back: &[T],
    s: usize,
    v_out: &[T],
    c: usize,
    v_t_in: Option<&[T]>,
    need_transmittance: bool,
    need_back: bool,
) -> Result<CompositeGrads<T>> {
    let p = transmittance.len();
    // The transmittance's written whole below; the back's only on its first C channels.
    let mut v_t = need_transmittance
        .then(|| unwritten("transmittance gradient (P,)", p))
        .transpose()?;
    let mut v_back = need_back
        .then(|| zeroed("back gradient (P, S)", s * p))
        .transpose()?;
    let tasks = p.div_ceil(CHUNK);
    let t_chunks = optional_chunks(v_t.as_deref_mut(), CHUNK, tasks);
    let back_chunks = optional_chunks(v_back.as_deref_mut(), s * CHUNK, tasks);
    t_chunks
        .into_par_iter()
        .zip(back_chunks)
        .enumerate()
        .for_each(|(chunk, (mut v_t, mut v_back))| {
            let first = chunk * CHUNK;
            for i in 0..CHUNK.min(p - first) {
                let px = first + i;
                let g = &v_out[c * px..c * px + c];
                if let Some(v_t) = v_t.as_deref_mut() {
                    let behind = &back[s * px..s * px + c];
                    let mut dot = g[0] * behind[0];
                    for k in 1..c {
                        dot += g[k] * behind[k];
                    }
                    v_t[i].write(match v_t_in {
                        Some(v) => dot + v[px],
                        None => dot,
                    });
                }
                if let Some(v_back) = v_back.as_deref_mut() {
                    let t = transmittance[px];
                    for k in 0..c {
                        v_back[s * i + k] = t * g[k];
                    }
                }
            }
        });
    Ok(CompositeGrads {
        // SAFETY: the chunks partition the pixels, and each pixel's entry was written.
        v_transmittance: v_t.map(|v| unsafe { assume_written(v) }),
        v_back,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{on_threads, Rng};

    fn inputs<'a>(
        front: &'a [f64],
        transmittance: &'a [f64],
        back: &'a [f64],
        s: usize,
    ) -> CompositeInputs<'a, f64> {
        CompositeInputs {
            front,
            transmittance,
            back,
            back_channels: s,
        }
    }

    fn case(p: usize, s: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
        let mut rng = Rng::new(1);
        (
            rng.vec(3 * p, 0.0, 1.0),
            rng.vec(p, 0.0, 1.0),
            rng.vec(s * p, 0.0, 1.0),
            rng.vec(3 * p, -1.0, 1.0),
        )
    }

    #[test]
    fn forward_and_adjoint_are_the_formula() {
        let (p, s) = (10_000, 4);
        let (front, t, back, g) = case(p, s);
        let inputs = inputs(&front, &t, &back, s);
        let out = composite_forward(&inputs).unwrap();
        let grads = composite_backward(&inputs, &g, true, true).unwrap();
        let (v_t, v_back) = (grads.v_transmittance.unwrap(), grads.v_back.unwrap());
        for px in 0..p {
            let mut dot = 0.0;
            for c in 0..3 {
                assert_eq!(out[3 * px + c], front[3 * px + c] + t[px] * back[s * px + c]);
                assert_eq!(v_back[s * px + c], t[px] * g[3 * px + c]);
                dot += g[3 * px + c] * back[s * px + c];
            }
            assert!((v_t[px] - dot).abs() <= 1e-15);
            assert_eq!(v_back[s * px + 3], 0.0, "no gradient past the colour");
        }
        let only_t = composite_backward(&inputs, &g, true, false).unwrap();
        assert!(only_t.v_back.is_none() && only_t.v_transmittance.unwrap() == v_t);
    }

    #[test]
    fn same_bits_for_any_thread_count() {
        let (p, s) = (20_000, 3);
        let (front, t, back, g) = case(p, s);
        let inputs = inputs(&front, &t, &back, s);
        let run = || {
            let out = composite_forward(&inputs).unwrap();
            let grads = composite_backward(&inputs, &g, true, true).unwrap();
            (out, grads.v_transmittance, grads.v_back)
        };
        let one = on_threads(1, run);
        for threads in [2, 3] {
            assert!(on_threads(threads, run) == one, "{threads} threads");
        }
    }

    #[test]
    fn bad_lengths_are_named() {
        let (front, t, back, g) = case(5, 4);
        let inputs = inputs(&front, &t, &back, 2);
        assert!(composite_forward(&inputs)
            .unwrap_err()
            .to_string()
            .contains("back"));
        let inputs = CompositeInputs {
            back_channels: 4,
            front: &front[..14],
            ..inputs
        };
        assert!(composite_forward(&inputs)
            .unwrap_err()
            .to_string()
            .contains("front"));
        let inputs = CompositeInputs {
            front: &front,
            ..inputs
        };
        let err = composite_backward(&inputs, &g[..3], true, true).unwrap_err();
        assert!(err.to_string().contains("v_out"));
    }
}
