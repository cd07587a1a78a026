//! The mesh branch works on its covered pixels only; these two ops go from the image to
//! that list and back.
//!
//! - [`covered_pixels`]: the flat indices of the pixels a triangle covers, increasing
//!   (torch's `(tri_id >= 0).nonzero()` is a serial pass plus a mask image).
//! - [`scatter_pixels_forward`]: an image filled with a background value, with listed
//!   pixels set to their rows (torch's `repeat` + `index_put_` are two serial passes over
//!   the image), and its adjoint: the rows' gradient is the image gradient gathered at the
//!   listed pixels, the background's the image gradient summed over the others. The rows
//!   may be narrower than the image, its last channels at listed pixels a constant `fill`
//!   (the mesh's colour with alpha 1: no concatenated `(P, 4)` copy, nor its gradient's
//!   slice).
//!
//! Work is cut into fixed chunks of pixels and partial sums are merged in chunk order, so
//! results are the same bits for any thread count.

use rayon::prelude::*;

use crate::error::{check_len, first_pair_where, Error, Result};
use crate::memory::{assume_written, copy_short, unwritten, zeroed};
use crate::Real;

/// Pixels per parallel work item.
const CHUNK: usize = 8192;

/// `(P,)` flat indices `y·W + x` of the pixels whose `tri_id` is not −1 (any value ≥ 0
/// counts as covered), increasing.
pub fn covered_pixels(tri_id: &[i32]) -> Result<Vec<i64>> {
    // Two parallel passes: each chunk's count (a branch-free sum that vectorises), then
    // each chunk's indices straight into its own slice of the exactly sized list — no
    // per-chunk vectors growing, and no serial concatenation of them.
    let counts: Vec<usize> = tri_id
        .par_chunks(CHUNK)
        .map(|ids| ids.iter().map(|&id| usize::from(id >= 0)).sum())
        .collect();
    let mut pixels = unwritten("covered pixels (P,)", counts.iter().sum())?;
    let mut slices = Vec::with_capacity(counts.len());
    let mut rest = &mut pixels[..];
    for &count in &counts {
        let (head, tail) = rest.split_at_mut(count);
        slices.push(head);
        rest = tail;
    }
    slices
        .into_par_iter()
        .zip(tri_id.par_chunks(CHUNK))
        .enumerate()
        .for_each(|(chunk, (out, ids))| {
            let covered = ((chunk * CHUNK) as i64..)
                .zip(ids)
                .filter(|&(_, &id)| id >= 0)
                .map(|(p, _)| p);
            for (slot, p) in out.iter_mut().zip(covered) {
                slot.write(p);
            }
        });
    // SAFETY: slice k holds exactly chunk k's count of entries, and chunk k's pass wrote
    // one per covered pixel of that chunk: every entry was written.
    Ok(unsafe { assume_written(pixels) })
}

/// What [`scatter_pixels_forward`] and its adjoint read.
#[derive(Debug, Clone, Copy)]
pub struct ScatterInputs<'a> {
    /// `(P,)` flat pixel indices, strictly increasing (each pixel listed once), in
    /// `[0, pixel_count)`.
    pub pixels: &'a [i64],
    /// `H·W`.
    pub pixel_count: usize,
    /// `C`, the rows' and the background's length.
    pub channels: usize,
}

impl ScatterInputs<'_> {
    /// Checks the list; returns `P`.
    fn validate(&self) -> Result<usize> {
        if self.channels == 0 {
            return Err(Error::Invalid {
                arg: "values",
                reason: "needs at least one channel".into(),
            });
        }
        let n = self.pixel_count as i64;
        let bad = first_pair_where(self.pixels, |a, b| a >= b)
            .or_else(|| (self.pixels.first().is_some_and(|&p| p < 0)).then_some(0))
            .or_else(|| (self.pixels.last().is_some_and(|&p| p >= n)).then(|| self.pixels.len() - 1));
        if let Some(i) = bad {
            return Err(Error::Invalid {
                arg: "pixels",
                reason: format!(
                    "must be strictly increasing flat indices in [0, {n}), got {} at index {i}{}",
                    self.pixels[i],
                    if i > 0 {
                        format!(" after {}", self.pixels[i - 1])
                    } else {
                        String::new()
                    }
                ),
            });
        }
        Ok(self.pixels.len())
    }

    /// The rows' width `C − K` for a constant tail of `fill` channels (`K < C`).
    fn value_channels(&self, fill: usize) -> Result<usize> {
        if fill >= self.channels {
            return Err(Error::Invalid {
                arg: "fill",
                reason: format!(
                    "{fill} channels leave none for the values of a {}-channel image",
                    self.channels
                ),
            });
        }
        Ok(self.channels - fill)
    }

    /// The entries of `pixels` that fall in pixel chunk `chunk`, and the first one's index.
    fn listed_in(&self, chunk: usize) -> (usize, &[i64]) {
        let (start, end) = ((chunk * CHUNK) as i64, ((chunk + 1) * CHUNK) as i64);
        let first = self.pixels.partition_point(|&p| p < start);
        let last = first + self.pixels[first..].partition_point(|&p| p < end);
        (first, &self.pixels[first..last])
    }
}

/// `(H·W, C)`: `background` everywhere; at pixel `pixels[i]`, `values[i]` then `fill`.
/// `values (P, C − K)`, `fill (K,)` and `background (C,)` are data (non-finite values pass
/// through).
pub fn scatter_pixels_forward<T: Real>(
    inputs: &ScatterInputs<'_>,
    values: &[T],
    fill: &[T],
    background: &[T],
) -> Result<Vec<T>> {
    let p = inputs.validate()?;
    let c = inputs.channels;
    let w = inputs.value_channels(fill.len())?;
    check_len("values", values, p * w, &format!("(P, C − K) = ({p}, {w})"))?;
    check_len("background", background, c, &format!("(C,) = ({c},)"))?;
    let mut image = unwritten("scattered image (H, W, C)", inputs.pixel_count * c)?;
    // One chunk of background, copied in one go (per pixel, a `c`-long copy is a call).
    let template = background.repeat(CHUNK);
    image
        .par_chunks_mut(CHUNK * c)
        .enumerate()
        .for_each(|(chunk, out)| {
            for (pixel, &value) in out.iter_mut().zip(&template) {
                pixel.write(value);
            }
            let first = chunk * CHUNK;
            let (start, listed) = inputs.listed_in(chunk);
            for (i, &q) in listed.iter().enumerate() {
                let row = &mut out[(q as usize - first) * c..];
                copy_short(row, &values[(start + i) * w..], w);
                copy_short(&mut row[w..], fill, fill.len());
            }
        });
    // SAFETY: the chunks partition the image, and each was first written whole with the
    // background (the template is as long as a chunk).
    Ok(unsafe { assume_written(image) })
}

/// The gradients of [`scatter_pixels_backward`], `None` where not asked for.
#[derive(Debug, Clone)]
pub struct ScatterGrads<T> {
    /// `(P, C − K)`: the image gradient at the listed pixels, less the fill's channels.
    pub v_values: Option<Vec<T>>,
    /// `(C,)`: the image gradient summed over the pixels not listed.
    pub v_background: Option<Vec<T>>,
}

/// Adjoint of [`scatter_pixels_forward`] given the image gradient `v_image (H·W, C)`
/// (data, as the forward's values: non-finite values pass through) and the forward's
/// `fill` length `K` (the constant channels pass no gradient).
pub fn scatter_pixels_backward<T: Real>(
    inputs: &ScatterInputs<'_>,
    v_image: &[T],
    fill: usize,
    need_values: bool,
    need_background: bool,
) -> Result<ScatterGrads<T>> {
    let p = inputs.validate()?;
    let c = inputs.channels;
    let w = inputs.value_channels(fill)?;
    let n = inputs.pixel_count;
    check_len("v_image", v_image, n * c, &format!("(H·W, C) = ({n}, {c})"))?;
    let v_values = need_values
        .then(|| -> Result<Vec<T>> {
            let mut rows = zeroed("scatter values gradient (P, C − K)", p * w)?;
            rows.par_chunks_mut(CHUNK * w)
                .zip(inputs.pixels.par_chunks(CHUNK))
                .for_each(|(rows, pixels)| {
                    for (row, &q) in rows.chunks_exact_mut(w).zip(pixels) {
                        copy_short(row, &v_image[q as usize * c..], w);
                    }
                });
            Ok(rows)
        })
        .transpose()?;
    let v_background = need_background.then(|| {
        let partials: Vec<Vec<T>> = v_image
            .par_chunks(CHUNK * c)
            .enumerate()
            .map(|(chunk, grads)| {
                let first = chunk * CHUNK;
                let mut listed = inputs.listed_in(chunk).1.iter().peekable();
                let mut sum = vec![T::zero(); c];
                for (i, g) in grads.chunks_exact(c).enumerate() {
                    if listed.next_if(|&&q| q as usize == first + i).is_some() {
                        continue;
                    }
                    for (s, x) in sum.iter_mut().zip(g) {
                        *s += *x;
                    }
                }
                sum
            })
            .collect();
        crate::parallel::sum_in_order(&partials, c)
    });
    Ok(ScatterGrads {
        v_values,
        v_background,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn covered_pixels_lists_non_negative_ids_in_order() {
        let n = 3 * CHUNK + 17;
        let tri_id: Vec<i32> = (0..n)
            .map(|i| {
                if i % 5 == 0 || i % 7 == 3 {
                    (i % 11) as i32
                } else {
                    -1
                }
            })
            .collect();
        let expected: Vec<i64> = (0..n as i64).filter(|&i| tri_id[i as usize] >= 0).collect();
        assert_eq!(covered_pixels(&tri_id).unwrap(), expected);
        assert!(covered_pixels(&[]).unwrap().is_empty());
        assert!(covered_pixels(&[-1; 10]).unwrap().is_empty());
        // Chunks wholly covered and wholly empty between mixed ones: each chunk's slice of
        // the list has exactly its own count.
        let blocks: Vec<i32> = (0..4 * CHUNK + 5)
            .map(|i| match i / CHUNK {
                1 => 7,
                2 => -1,
                _ => (i % 3) as i32 - 1,
            })
            .collect();
        let expected: Vec<i64> = (0..blocks.len() as i64)
            .filter(|&i| blocks[i as usize] >= 0)
            .collect();
        assert_eq!(covered_pixels(&blocks).unwrap(), expected);
    }

    #[test]
    fn scatter_and_its_adjoint_against_a_direct_loop() {
        let (n, c) = (2 * CHUNK + 5, 3);
        let pixels: Vec<i64> = (0..n as i64).filter(|i| i % 3 != 1).collect();
        let values: Vec<f64> = (0..pixels.len() * c).map(|i| i as f64 * 0.5).collect();
        let background = [0.25, -1.0, 2.0];
        let inputs = ScatterInputs {
            pixels: &pixels,
            pixel_count: n,
            channels: c,
        };
        let image = scatter_pixels_forward(&inputs, &values, &[], &background).unwrap();
        let mut expected: Vec<f64> = background.repeat(n);
        for (row, &q) in pixels.iter().enumerate() {
            let q = q as usize;
            expected[q * c..(q + 1) * c].copy_from_slice(&values[row * c..(row + 1) * c]);
        }
        assert_eq!(image, expected);

        let v_image: Vec<f64> = (0..n * c).map(|i| ((i * 37) % 101) as f64 - 50.0).collect();
        let g = scatter_pixels_backward(&inputs, &v_image, 0, true, true).unwrap();
        let v_values: Vec<f64> = pixels
            .iter()
            .flat_map(|&q| v_image[q as usize * c..(q as usize + 1) * c].to_vec())
            .collect();
        assert_eq!(g.v_values.unwrap(), v_values);
        let mut v_background = vec![0.0; c];
        for q in (0..n).filter(|&q| q % 3 == 1) {
            for k in 0..c {
                v_background[k] += v_image[q * c + k];
            }
        }
        assert_eq!(g.v_background.unwrap(), v_background); // integers: exact in any order
    }

    #[test]
    fn a_constant_fill_is_the_rows_widened_by_it() {
        // The rows (P, 3) with fill [1] against the rows (P, 4) with a column of ones: the
        // same image; the gradient is the wide rows' without their last column.
        let (n, c) = (2 * CHUNK + 9, 4);
        let pixels: Vec<i64> = (0..n as i64).filter(|i| i % 4 != 2).collect();
        let narrow: Vec<f32> = (0..pixels.len() * 3).map(|i| i as f32 * 0.25 - 7.0).collect();
        let wide: Vec<f32> = narrow
            .chunks_exact(3)
            .flat_map(|r| [r[0], r[1], r[2], 1.0])
            .collect();
        let background = [0.5f32, 0.25, -1.0, 0.0];
        let inputs = ScatterInputs {
            pixels: &pixels,
            pixel_count: n,
            channels: c,
        };
        let filled = scatter_pixels_forward(&inputs, &narrow, &[1.0], &background).unwrap();
        assert_eq!(
            filled,
            scatter_pixels_forward(&inputs, &wide, &[], &background).unwrap()
        );

        let v_image: Vec<f32> = (0..n * c).map(|i| ((i * 29) % 97) as f32 - 48.0).collect();
        let narrow_grad = scatter_pixels_backward(&inputs, &v_image, 1, true, true).unwrap();
        let wide_grad = scatter_pixels_backward(&inputs, &v_image, 0, true, true).unwrap();
        let expected: Vec<f32> = wide_grad
            .v_values
            .unwrap()
            .chunks_exact(4)
            .flat_map(|r| r[..3].to_vec())
            .collect();
        assert_eq!(narrow_grad.v_values.unwrap(), expected);
        assert_eq!(narrow_grad.v_background, wide_grad.v_background);
    }

    #[test]
    fn rejects_lists_that_are_not_strictly_increasing_or_out_of_range() {
        let check = |pixels: &[i64]| {
            let inputs = ScatterInputs {
                pixels,
                pixel_count: 10,
                channels: 1,
            };
            scatter_pixels_forward(&inputs, &vec![0.0f32; pixels.len()], &[], &[0.0])
        };
        assert!(check(&[0, 3, 9]).is_ok());
        for bad in [&[0, 3, 3][..], &[4, 2], &[-1, 2], &[2, 10]] {
            let err = check(bad).unwrap_err();
            assert!(
                matches!(err, Error::Invalid { arg: "pixels", .. }),
                "{bad:?}: {err}"
            );
        }
        let inputs = ScatterInputs {
            pixels: &[1],
            pixel_count: 10,
            channels: 2,
        };
        assert!(matches!(
            scatter_pixels_forward(&inputs, &[0.0f32; 3], &[], &[0.0, 0.0]),
            Err(Error::Shape { arg: "values", .. })
        ));
        for fill in [&[1.0f32, 2.0][..], &[1.0, 2.0, 3.0]] {
            assert!(matches!(
                scatter_pixels_forward(&inputs, &[], fill, &[0.0, 0.0]),
                Err(Error::Invalid { arg: "fill", .. })
            ));
            assert!(matches!(
                scatter_pixels_backward(&inputs, &[0.0f32; 20], fill.len(), true, true),
                Err(Error::Invalid { arg: "fill", .. })
            ));
        }
    }
}
