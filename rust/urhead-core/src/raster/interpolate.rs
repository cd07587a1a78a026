//! `interpolate`: per-vertex attributes → per-pixel attributes through the rasterizer's
//! barycentrics, `out = (1 − b1 − b2)·a0 + b1·a1 + b2·a2` (0 where no triangle), and its
//! adjoint with respect to the attributes and the barycentrics.

use rayon::prelude::*;

use super::runs::{merge_runs, TriangleRuns};
use super::{check_faces, check_tri_id, TILE_ROWS};
use crate::error::{check_finite, check_len, Error, Result};
use crate::memory::zeroed;
use crate::Real;

/// Gradients of [`interpolate_backward`]; a field is `Some` exactly when it was asked for.
#[derive(Debug, Clone, Default)]
pub struct InterpolateGrads<T> {
    /// `(V, C)`
    pub v_attr: Option<Vec<T>>,
    /// `(H, W, 2)`
    pub v_bary: Option<Vec<T>>,
}

/// The shapes shared by both passes.
struct Dims {
    channels: usize,
    height: usize,
    width: usize,
}

fn validate<T: Real>(
    attr: &[T],
    channels: usize,
    faces: &[i32],
    tri_id: &[i32],
    bary: &[T],
    height: usize,
    width: usize,
) -> Result<Dims> {
    if channels == 0 || attr.len() % channels != 0 {
        return Err(Error::Shape {
            arg: "attr",
            expected: "(V, C) with C ≥ 1".into(),
            got: format!("{} elements with C = {channels}", attr.len()),
        });
    }
    let num_faces = check_faces("faces", faces, attr.len() / channels, "V")?;
    check_tri_id(tri_id, height, width, num_faces)?;
    check_len(
        "bary",
        bary,
        height * width * 2,
        &format!("(H, W, 2) = ({height}, {width}, 2)"),
    )?;
    check_finite("attr", attr)?;
    check_finite("bary", bary)?;
    Ok(Dims {
        channels,
        height,
        width,
    })
}

/// `attr (V, C)`, `faces (F, 3)` indexing `attr` (e.g. UV faces for UV coordinates),
/// `tri_id (H, W)` and `bary (H, W, 2)` from the rasterizer → `(H, W, C)`.
pub fn interpolate_forward<T: Real>(
    attr: &[T],
    channels: usize,
    faces: &[i32],
    tri_id: &[i32],
    bary: &[T],
    height: usize,
    width: usize,
) -> Result<Vec<T>> {
    let d = validate(attr, channels, faces, tri_id, bary, height, width)?;
    let c = d.channels;
    let mut out = zeroed("interpolated image", d.height * d.width * c)?;
    out.par_chunks_mut(TILE_ROWS * d.width * c)
        .enumerate()
        .for_each(|(tile, out)| {
            let first = tile * TILE_ROWS * d.width;
            for (i, px) in out.chunks_exact_mut(c).enumerate() {
                let idx = first + i;
                let tri = tri_id[idx];
                if tri < 0 {
                    continue;
                }
                let f = &faces[3 * tri as usize..3 * tri as usize + 3];
                let (b1, b2) = (bary[2 * idx], bary[2 * idx + 1]);
                let b0 = T::one() - b1 - b2;
                let (a0, a1, a2) = (row(attr, f[0], c), row(attr, f[1], c), row(attr, f[2], c));
                for k in 0..c {
                    px[k] = b0 * a0[k] + b1 * a1[k] + b2 * a2[k];
                }
            }
        });
    Ok(out)
}

#[inline(always)]
fn row<T>(attr: &[T], v: i32, c: usize) -> &[T] {
    &attr[v as usize * c..(v as usize + 1) * c]
}

/// Adjoint of [`interpolate_forward`] given `v_out (H, W, C)`; computes the gradients
/// flagged in `need_attr` / `need_bary` only. The attribute gradient is accumulated per
/// tile and triangle, then merged in a fixed order (deterministic for any thread count).
pub fn interpolate_backward<T: Real>(
    attr: &[T],
    channels: usize,
    faces: &[i32],
    tri_id: &[i32],
    bary: &[T],
    height: usize,
    width: usize,
    v_out: &[T],
    need_attr: bool,
    need_bary: bool,
) -> Result<InterpolateGrads<T>> {
    let d = validate(attr, channels, faces, tri_id, bary, height, width)?;
    let c = d.channels;
    let (h, w) = (d.height, d.width);
    check_len("v_out", v_out, h * w * c, &format!("(H, W, C) = ({h}, {w}, {c})"))?;
    let num_faces = faces.len() / 3;
    let v_attr = need_attr.then(|| {
        let runs: Vec<TriangleRuns<T>> = v_out
            .par_chunks(TILE_ROWS * w * c)
            .enumerate()
            .map(|(tile, g)| {
                let mut runs = TriangleRuns::new(3 * c);
                let first = tile * TILE_ROWS * w;
                for (i, g) in g.chunks_exact(c).enumerate() {
                    let idx = first + i;
                    let tri = tri_id[idx];
                    if tri < 0 {
                        continue;
                    }
                    let (b1, b2) = (bary[2 * idx], bary[2 * idx + 1]);
                    let b = [T::one() - b1 - b2, b1, b2];
                    let slot = runs.slot(tri as u32);
                    for k in 0..3 {
                        for (s, gk) in slot[k * c..(k + 1) * c].iter_mut().zip(g) {
                            *s += b[k] * *gk;
                        }
                    }
                }
                runs
            })
            .collect();
        let per_tri = merge_runs(&runs, num_faces, 3 * c);
        let mut v_attr = vec![T::zero(); attr.len()];
        for (f, sums) in faces.chunks_exact(3).zip(per_tri.chunks_exact(3 * c)) {
            for k in 0..3 {
                let dst = &mut v_attr[f[k] as usize * c..(f[k] as usize + 1) * c];
                for (a, s) in dst.iter_mut().zip(&sums[k * c..(k + 1) * c]) {
                    *a += *s;
                }
            }
        }
        v_attr
    });
    let v_bary = need_bary
        .then(|| -> Result<Vec<T>> {
            let mut v_bary = zeroed("barycentric gradient", h * w * 2)?;
            v_bary
                .par_chunks_mut(TILE_ROWS * w * 2)
                .enumerate()
                .for_each(|(tile, vb)| {
                    let first = tile * TILE_ROWS * w;
                    for (i, vb) in vb.chunks_exact_mut(2).enumerate() {
                        let idx = first + i;
                        let tri = tri_id[idx];
                        if tri < 0 {
                            continue;
                        }
                        let f = &faces[3 * tri as usize..3 * tri as usize + 3];
                        let (a0, a1, a2) = (row(attr, f[0], c), row(attr, f[1], c), row(attr, f[2], c));
                        let g = &v_out[idx * c..(idx + 1) * c];
                        let (mut d1, mut d2) = (T::zero(), T::zero());
                        for k in 0..c {
                            d1 += g[k] * (a1[k] - a0[k]);
                            d2 += g[k] * (a2[k] - a0[k]);
                        }
                        vb[0] = d1;
                        vb[1] = d2;
                    }
                });
            Ok(v_bary)
        })
        .transpose()?;
    Ok(InterpolateGrads { v_attr, v_bary })
}
