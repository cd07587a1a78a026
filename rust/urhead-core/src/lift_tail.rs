//! The maps a Gaussian's lift reads from its map row, split out of the `(N, C)` rows in one
//! pass, and their gradients joined back into the rows' tail in one pass.
//!
//! A Gaussian's row holds its SH colour, then the tail: normal N (3 channels), displacement
//! D, opacity O, scale S (3), possibly more maps (the offset E, shading maps). The lift
//! needs N, the lift `D (+ E)`, raw S and O (exponentiated and squashed by the caller) as
//! contiguous arrays; column by column that is a strided copy per map, each over every
//! row's cache lines. Forward and adjoint are plain copies, one IEEE addition (`D + E`) and
//! the products of the activations' derivatives, so they give the same bits as the same
//! operations done one tensor at a time.

use rayon::prelude::*;

use crate::error::{check_len, Error, Result};
use crate::memory::zeroed;
use crate::parallel::optional_chunks;
use crate::Real;

/// Rows per rayon task; fixed (every row is independent).
const CHUNK: usize = 1024;
/// The fixed maps' places in the tail.
const NORMAL: usize = 0;
const DISPLACEMENT: usize = 3;
const OPACITY: usize = 4;
const SCALE: usize = 5;
/// The tail's width without optional maps.
const FIXED_WIDTH: usize = 8;

/// Where the tail sits in a row.
#[derive(Debug, Clone, Copy)]
pub struct TailLayout {
    /// `C`, the row's channels.
    pub channels: usize,
    /// The tail's first channel (the colour's channel count).
    pub start: usize,
    /// The offset map E's channel in the tail, if the layout has one.
    pub offset: Option<usize>,
}

impl TailLayout {
    fn width(&self) -> usize {
        self.channels.saturating_sub(self.start)
    }

    fn validate(&self) -> Result<()> {
        let width = self.width();
        let offset_ok = self.offset.is_none_or(|e| e >= FIXED_WIDTH && e < width);
        if self.start > self.channels || width < FIXED_WIDTH || !offset_ok {
            return Err(Error::Invalid {
                arg: "layout",
                reason: format!(
                    "a tail of at least {FIXED_WIDTH} channels (N, D, O, S) from channel {} of {} \
                     with the offset (if any) after them is needed, got offset {:?}",
                    self.start, self.channels, self.offset
                ),
            });
        }
        Ok(())
    }
}

/// The lift's maps, contiguous.
#[derive(Debug, Clone)]
pub struct TailColumns<T> {
    /// `(N, 3)` the normal map N.
    pub normals: Vec<T>,
    /// `(N,)` the lift along the normal: D, or D + E with an offset map.
    pub lift: Vec<T>,
    /// `(N, 3)` the scale map S (log standard deviations).
    pub scales: Vec<T>,
    /// `(N,)` the opacity map O (logits).
    pub opacities: Vec<T>,
    /// `(N,)` the offset map E, with one.
    pub offset: Option<Vec<T>>,
}

/// Splits `rows (N, C)` into the lift's maps.
pub fn split_tail<T: Real>(rows: &[T], layout: &TailLayout) -> Result<TailColumns<T>> {
    layout.validate()?;
    let c = layout.channels;
    if rows.len() % c != 0 {
        return Err(Error::Shape {
            arg: "rows",
            expected: format!("(N, {c})"),
            got: format!("{} elements", rows.len()),
        });
    }
    let n = rows.len() / c;
    let mut out = TailColumns {
        normals: zeroed("normals (N, 3)", 3 * n)?,
        lift: zeroed("lift (N,)", n)?,
        scales: zeroed("scales (N, 3)", 3 * n)?,
        opacities: zeroed("opacities (N,)", n)?,
        offset: layout.offset.map(|_| zeroed("offset (N,)", n)).transpose()?,
    };
    let offset_chunks = optional_chunks(out.offset.as_deref_mut(), CHUNK, n.div_ceil(CHUNK));
    rows.par_chunks(CHUNK * c)
        .zip(out.normals.par_chunks_mut(3 * CHUNK))
        .zip(out.lift.par_chunks_mut(CHUNK))
        .zip(out.scales.par_chunks_mut(3 * CHUNK))
        .zip(out.opacities.par_chunks_mut(CHUNK))
        .zip(offset_chunks)
        .for_each(|(((((rows, normals), lift), scales), opacities), mut offset)| {
            for (i, row) in rows.chunks_exact(c).enumerate() {
                let tail = &row[layout.start..];
                normals[3 * i..3 * i + 3].copy_from_slice(&tail[NORMAL..NORMAL + 3]);
                scales[3 * i..3 * i + 3].copy_from_slice(&tail[SCALE..SCALE + 3]);
                opacities[i] = tail[OPACITY];
                lift[i] = match (layout.offset, offset.as_deref_mut()) {
                    (Some(e), Some(offset)) => {
                        offset[i] = tail[e];
                        tail[DISPLACEMENT] + tail[e]
                    }
                    _ => tail[DISPLACEMENT],
                };
            }
        });
    Ok(out)
}

/// The gradients of the lift's maps (each `None` when none came back).
#[derive(Debug, Clone, Copy, Default)]
pub struct TailGrads<'a, T> {
    /// `(N, 3)` and `(N,)`: the lift geometry's gradients of N and of the lift, together.
    pub normals_and_lift: Option<(&'a [T], &'a [T])>,
    /// `(N, 3)` the gradient of `exp(S)`, and `exp(S)`.
    pub scales: Option<(&'a [T], &'a [T])>,
    /// `(N,)` the gradient of `sigmoid(O)`, and `sigmoid(O)`.
    pub opacities: Option<(&'a [T], &'a [T])>,
    /// `(N,)` the gradient of E as an output of its own.
    pub offset: Option<&'a [T]>,
}

/// The tail's gradient `(N, C − start)`: N's, D's (and E's, which the lift also moves)
/// from the lift, `v·exp(S)` for S, `v·(1 − σ)·σ` for O, plus E's own; zero elsewhere.
pub fn join_tail_grad<T: Real>(n: usize, layout: &TailLayout, grads: &TailGrads<'_, T>) -> Result<Vec<T>> {
    layout.validate()?;
    let width = layout.width();
    if let Some((v_normals, v_lift)) = grads.normals_and_lift {
        check_len("v_normals", v_normals, 3 * n, &format!("(N, 3) = ({n}, 3)"))?;
        check_len("v_lift", v_lift, n, &format!("(N,) = ({n},)"))?;
    }
    for (arg, pair, per_row) in [("v_scales", grads.scales, 3), ("v_opacities", grads.opacities, 1)] {
        if let Some((v, values)) = pair {
            check_len(arg, v, per_row * n, &format!("({n}, {per_row})"))?;
            check_len(arg, values, per_row * n, &format!("({n}, {per_row})"))?;
        }
    }
    if let Some(v) = grads.offset {
        check_len("v_offset", v, n, &format!("(N,) = ({n},)"))?;
        if layout.offset.is_none() {
            return Err(Error::Invalid {
                arg: "v_offset",
                reason: "the layout has no offset map".into(),
            });
        }
    }
    let mut out = zeroed("tail gradient (N, W)", n * width)?;
    out.par_chunks_mut(CHUNK * width.max(1))
        .enumerate()
        .for_each(|(k, rows)| {
            for (i, row) in rows.chunks_exact_mut(width).enumerate() {
                let g = k * CHUNK + i;
                if let Some((v_normals, v_lift)) = grads.normals_and_lift {
                    row[NORMAL..NORMAL + 3].copy_from_slice(&v_normals[3 * g..3 * g + 3]);
                    row[DISPLACEMENT] = v_lift[g];
                    if let Some(e) = layout.offset {
                        row[e] = v_lift[g];
                    }
                }
                if let Some((v, scales)) = grads.scales {
                    for a in 0..3 {
                        row[SCALE + a] = v[3 * g + a] * scales[3 * g + a]; // exp's derivative
                    }
                }
                if let Some((v, sigma)) = grads.opacities {
                    row[OPACITY] = v[g] * (T::one() - sigma[g]) * sigma[g]; // sigmoid's
                }
                if let (Some(v), Some(e)) = (grads.offset, layout.offset) {
                    row[e] += v[g];
                }
            }
        });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;

    /// Rows of 12 channels: 2 of colour, the 8 fixed maps, then E at tail channel 9, and
    /// one more.
    fn rows(n: usize) -> (Vec<f64>, TailLayout) {
        let layout = TailLayout {
            channels: 12,
            start: 2,
            offset: Some(8),
        };
        (Rng::new(5).vec(n * 12, -2.0, 2.0), layout)
    }

    #[test]
    fn split_copies_each_map_and_adds_the_offset_to_the_lift() {
        let n = 2500; // more than two chunks
        let (rows, layout) = rows(n);
        let out = split_tail(&rows, &layout).unwrap();
        let offset = out.offset.as_ref().unwrap();
        for g in 0..n {
            let tail = &rows[12 * g + 2..12 * g + 12];
            assert_eq!(out.normals[3 * g..3 * g + 3], tail[0..3]);
            assert_eq!(out.scales[3 * g..3 * g + 3], tail[5..8]);
            assert_eq!(out.opacities[g], tail[4]);
            assert_eq!(offset[g], tail[8]);
            assert_eq!(out.lift[g].to_bits(), (tail[3] + tail[8]).to_bits());
        }
        let plain = TailLayout {
            offset: None,
            ..layout
        };
        let out = split_tail(&rows, &plain).unwrap();
        assert!(out.offset.is_none());
        assert!((0..n).all(|g| out.lift[g] == rows[12 * g + 5]));
    }

    #[test]
    fn join_places_each_gradient_and_the_activations_derivatives() {
        let n = 1500;
        let (_, layout) = rows(n);
        let mut rng = Rng::new(6);
        let [v_normals, v_scales, scales]: [Vec<f64>; 3] = std::array::from_fn(|_| rng.vec(3 * n, -1.0, 1.0));
        let [v_lift, v_opacities, sigma, v_offset]: [Vec<f64>; 4] =
            std::array::from_fn(|_| rng.vec(n, 0.0, 1.0));
        let grads = TailGrads {
            normals_and_lift: Some((&v_normals, &v_lift)),
            scales: Some((&v_scales, &scales)),
            opacities: Some((&v_opacities, &sigma)),
            offset: Some(&v_offset),
        };
        let out = join_tail_grad(n, &layout, &grads).unwrap();
        for g in 0..n {
            let row = &out[10 * g..10 * g + 10];
            assert_eq!(row[0..3], v_normals[3 * g..3 * g + 3]);
            assert_eq!(row[3], v_lift[g]);
            assert_eq!(row[4], v_opacities[g] * (1.0 - sigma[g]) * sigma[g]);
            for a in 0..3 {
                assert_eq!(row[5 + a], v_scales[3 * g + a] * scales[3 * g + a]);
            }
            assert_eq!(row[8], v_lift[g] + v_offset[g]);
            assert_eq!(row[9], 0.0);
        }
        let none = join_tail_grad::<f64>(n, &layout, &TailGrads::default()).unwrap();
        assert!(none.iter().all(|x| *x == 0.0) && none.len() == 10 * n);
    }

    #[test]
    fn bad_layouts_and_lengths_are_refused_by_name() {
        let (rows, layout) = rows(4);
        for bad in [
            TailLayout { start: 5, ..layout },
            TailLayout {
                offset: Some(3),
                ..layout
            },
            TailLayout {
                offset: Some(10),
                ..layout
            },
        ] {
            assert!(matches!(
                split_tail(&rows, &bad),
                Err(Error::Invalid { arg: "layout", .. })
            ));
        }
        assert!(matches!(
            split_tail(&rows[..13], &layout),
            Err(Error::Shape { arg: "rows", .. })
        ));
        let short = [0.0; 5];
        let grads = TailGrads {
            normals_and_lift: Some((&short, &short[..4])),
            ..TailGrads::default()
        };
        assert!(matches!(
            join_tail_grad(4, &layout, &grads),
            Err(Error::Shape { arg: "v_normals", .. })
        ));
        let plain = TailLayout {
            offset: None,
            ..layout
        };
        let grads = TailGrads {
            offset: Some(&short[..4]),
            ..TailGrads::default()
        };
        assert!(matches!(
            join_tail_grad(4, &plain, &grads),
            Err(Error::Invalid { arg: "v_offset", .. })
        ));
    }
}
