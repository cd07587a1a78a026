//! Tile compositing, backward.
//!
//! Per tile: (1) replay the forward front to back with the same [`TileState::visit_gaussian`],
//! recording for every contributing chunk its T before the sample (recomputed, never
//! divided out) and its contributing-lane mask; (2) walk the records back to front with
//! the scalar recurrence G_{i−1} = α_i·(v_C·c_i) + (1 − α_i)·G_i, G_last = v_C·bg + v_T, so
//! ∂L/∂α_i = T_i·(v_C·c_i − G_i); per (Gaussian, tile) the lane sums become one gradient
//! record at that intersection. (3) Each Gaussian sums its records in its fixed
//! row-major tile order. Long tile lists are replayed in segments from snapshots, which
//! bounds the scratch memory.

use rayon::prelude::*;

use super::binning::Binning;
use super::lanes::{Lanes, WIDTH};
use super::raster::{chunk_dx, row_terms, splats, Splat, TileState, SLOTS};
use super::{RasterInputs, SplatReal, ALPHA_MAX, TILE};
use crate::error::{check_len, Error, Result};
use crate::Real;
use num_traits::Zero;

/// Gaussians per replay segment: bounds the per-thread records to SEGMENT·32 chunks.
const SEGMENT: usize = 1024;
const CHUNKS_PER_ROW: usize = TILE / WIDTH;
/// Leading fields of a gradient record: v_mean2d (2), v_conic (3), v_opacity (1).
const RECORD_HEAD: usize = 6;

/// Gradients of the rasterizer's inputs.
#[derive(Debug, Clone)]
pub struct RasterGrads<T> {
    /// `(N, 2)` screen-space positional gradient (what densification accumulates).
    pub v_means2d: Vec<T>,
    /// `(N, 3)`
    pub v_conics: Vec<T>,
    /// `(N, C)`
    pub v_colors: Vec<T>,
    /// `(N,)`
    pub v_opacities: Vec<T>,
}

/// Per-thread scratch of the tile backward.
struct Scratch<L: Lanes> {
    rec_t: Vec<L>,
    rec_alpha: Vec<L>,
    rec_g: Vec<L>,
    rec_meta: Vec<(u8, u8)>,
    /// Records end of each Gaussian of the current segment.
    ends: Vec<u32>,
    snapshots: Vec<TileState<L>>,
    v_color: Vec<L>,
    big_g: [L; SLOTS],
    acc_color: Vec<L>,
}

pub fn rasterize_backward<T: SplatReal>(
    inputs: &RasterInputs<T>,
    binning: &Binning,
    v_image: Option<&[T]>,
    v_transmittance: Option<&[T]>,
) -> Result<RasterGrads<T>> {
    rasterize_backward_with::<T::Fast>(inputs, binning, v_image, v_transmittance)
}

pub fn rasterize_backward_with<L: Lanes>(
    inputs: &RasterInputs<L::Elem>,
    binning: &Binning,
    v_image: Option<&[L::Elem]>,
    v_transmittance: Option<&[L::Elem]>,
) -> Result<RasterGrads<L::Elem>> {
    inputs.validate()?;
    let (w, h, c, n) = (inputs.width, inputs.height, inputs.channels, inputs.num_gaussians);
    if binning.width != w || binning.height != h || binning.gaussian_offsets.len() != n + 1 {
        return Err(Error::Invalid {
            arg: "binning",
            reason: "was made for other inputs (image size or Gaussian count differ)".into(),
        });
    }
    if let Some(v) = v_image {
        check_len("v_image", v, w * h * c, &format!("(H, W, C) = ({h}, {w}, {c})"))?;
    }
    if let Some(v) = v_transmittance {
        check_len("v_transmittance", v, w * h, &format!("(H, W) = ({h}, {w})"))?;
    }
    let splats = splats(inputs);
    let rec_len = RECORD_HEAD + c;
    let mut records = vec![L::Elem::zero(); binning.num_intersections() * rec_len];
    let zero_bg = vec![L::Elem::zero(); c];
    let background = inputs.background.unwrap_or(&zero_bg);

    // One task per row of tiles; its records are a contiguous range of intersections.
    let mut row_records: Vec<&mut [L::Elem]> = Vec::with_capacity(binning.tiles_y);
    let mut rest = records.as_mut_slice();
    for ty in 0..binning.tiles_y {
        let lo = binning.tile_offsets[ty * binning.tiles_x] as usize;
        let hi = binning.tile_offsets[(ty + 1) * binning.tiles_x] as usize;
        let (mine, tail) = rest.split_at_mut((hi - lo) * rec_len);
        row_records.push(mine);
        rest = tail;
    }
    row_records.into_par_iter().enumerate().for_each_init(
        || Scratch::<L> {
            rec_t: Vec::new(),
            rec_alpha: Vec::new(),
            rec_g: Vec::new(),
            rec_meta: Vec::new(),
            ends: Vec::new(),
            snapshots: Vec::new(),
            v_color: vec![L::splat(L::Elem::zero()); c * SLOTS],
            big_g: [L::splat(L::Elem::zero()); SLOTS],
            acc_color: vec![L::splat(L::Elem::zero()); c],
        },
        |scratch, (tile_y, out)| {
            let row_base = binning.tile_offsets[tile_y * binning.tiles_x] as usize;
            for tile_x in 0..binning.tiles_x {
                let tile = tile_y * binning.tiles_x + tile_x;
                let (lo, hi) = (
                    binning.tile_offsets[tile] as usize,
                    binning.tile_offsets[tile + 1] as usize,
                );
                let tile_out = &mut out[(lo - row_base) * rec_len..(hi - row_base) * rec_len];
                backward_tile(
                    inputs,
                    &splats,
                    &binning.tile_gaussians[lo..hi],
                    tile_x,
                    tile_y,
                    background,
                    v_image,
                    v_transmittance,
                    scratch,
                    tile_out,
                );
            }
        },
    );

    // Per Gaussian, sum its intersection records in its fixed (row-major tile) order.
    let mut v_means2d = vec![L::Elem::zero(); n * 2];
    let mut v_conics = vec![L::Elem::zero(); n * 3];
    let mut v_colors = vec![L::Elem::zero(); n * c];
    let mut v_opacities = vec![L::Elem::zero(); n];
    const CHUNK: usize = 1024;
    v_means2d
        .par_chunks_mut(CHUNK * 2)
        .zip(v_conics.par_chunks_mut(CHUNK * 3))
        .zip(v_colors.par_chunks_mut(CHUNK * c))
        .zip(v_opacities.par_chunks_mut(CHUNK))
        .enumerate()
        .for_each(|(chunk, (((vm, vc), vcol), vo))| {
            let mut sum = vec![L::Elem::zero(); rec_len];
            for k in 0..vo.len() {
                let g = chunk * CHUNK + k;
                sum.fill(L::Elem::zero());
                let range = binning.gaussian_offsets[g] as usize..binning.gaussian_offsets[g + 1] as usize;
                for &pos in &binning.isect_of_gaussian[range] {
                    let r = &records[pos as usize * rec_len..(pos as usize + 1) * rec_len];
                    for (s, v) in sum.iter_mut().zip(r) {
                        *s += *v;
                    }
                }
                vm[k * 2..k * 2 + 2].copy_from_slice(&sum[0..2]);
                vc[k * 3..k * 3 + 3].copy_from_slice(&sum[2..5]);
                vo[k] = sum[5];
                vcol[k * c..(k + 1) * c].copy_from_slice(&sum[RECORD_HEAD..]);
            }
        });
    Ok(RasterGrads {
        v_means2d,
        v_conics,
        v_colors,
        v_opacities,
    })
}

/// Visits one Gaussian, recording T before the sample and the contributing lanes of every
/// chunk it contributes to.
#[inline(always)]
fn record_gaussian<L: Lanes>(st: &mut TileState<L>, s: &Splat<L::Elem>, scratch: &mut Scratch<L>) {
    let (rec_t, rec_alpha, rec_g, rec_meta) = (
        &mut scratch.rec_t,
        &mut scratch.rec_alpha,
        &mut scratch.rec_g,
        &mut scratch.rec_meta,
    );
    st.visit_gaussian(s, |slot, alpha, g, t, contrib| {
        let bits = L::mask_bits(contrib);
        if bits != 0 {
            rec_t.push(t);
            rec_alpha.push(alpha);
            rec_g.push(g);
            rec_meta.push((slot as u8, bits));
        }
    });
    scratch.ends.push(scratch.rec_t.len() as u32);
}

fn clear_records<L: Lanes>(scratch: &mut Scratch<L>) {
    scratch.rec_t.clear();
    scratch.rec_alpha.clear();
    scratch.rec_g.clear();
    scratch.rec_meta.clear();
    scratch.ends.clear();
}

fn backward_tile<L: Lanes>(
    inputs: &RasterInputs<L::Elem>,
    splats: &[Splat<L::Elem>],
    list: &[u32],
    tile_x: usize,
    tile_y: usize,
    background: &[L::Elem],
    v_image: Option<&[L::Elem]>,
    v_transmittance: Option<&[L::Elem]>,
    scratch: &mut Scratch<L>,
    out: &mut [L::Elem],
) {
    type E<L> = <L as Lanes>::Elem;
    let (w, h, c) = (inputs.width, inputs.height, inputs.channels);
    let rec_len = RECORD_HEAD + c;
    let zero = L::splat(E::<L>::zero());

    // Pass 1: front to back over the whole list, snapshotting every SEGMENT Gaussians.
    let mut st = TileState::<L>::new(inputs, tile_x, tile_y);
    scratch.snapshots.clear();
    let mut end = 0;
    while end < list.len() && st.num_active > 0 {
        if end % SEGMENT == 0 {
            scratch.snapshots.push(st.clone());
            clear_records(scratch);
        }
        record_gaussian(&mut st, &splats[list[end] as usize], scratch);
        end += 1;
    }
    if end == 0 {
        return;
    }

    // Per-pixel upstream gradients and G_last = v_C·bg + v_T.
    let (x0, y0) = (tile_x * TILE, tile_y * TILE);
    for slot in 0..SLOTS {
        let (row, ch) = (slot / CHUNKS_PER_ROW, slot % CHUNKS_PER_ROW);
        let y = y0 + row;
        let mut g_last = [E::<L>::zero(); WIDTH];
        for k in 0..c {
            let mut vc = [E::<L>::zero(); WIDTH];
            for (i, v) in vc.iter_mut().enumerate() {
                let x = x0 + ch * WIDTH + i;
                if x < w && y < h {
                    *v = v_image.map_or(E::<L>::zero(), |g| g[(y * w + x) * c + k]);
                    g_last[i] += *v * background[k];
                }
            }
            scratch.v_color[k * SLOTS + slot] = L::from_array(vc);
        }
        for (i, gl) in g_last.iter_mut().enumerate() {
            let x = x0 + ch * WIDTH + i;
            if x < w && y < h {
                *gl += v_transmittance.map_or(E::<L>::zero(), |g| g[y * w + x]);
            }
        }
        scratch.big_g[slot] = L::from_array(g_last);
    }

    // Pass 2: segments back to front; earlier segments are replayed from their snapshot.
    let num_segments = scratch.snapshots.len();
    for seg in (0..num_segments).rev() {
        let k0 = seg * SEGMENT;
        let k1 = (k0 + SEGMENT).min(end);
        if seg + 1 != num_segments {
            let mut replay_state = scratch.snapshots[seg].clone();
            clear_records(scratch);
            for &g in &list[k0..k1] {
                record_gaussian(&mut replay_state, &splats[g as usize], scratch);
            }
        }
        for k in (k0..k1).rev() {
            let r1 = scratch.ends[k - k0] as usize;
            let r0 = if k == k0 {
                0
            } else {
                scratch.ends[k - k0 - 1] as usize
            };
            if r0 == r1 {
                continue;
            }
            let g = list[k] as usize;
            let s = &splats[g];
            let color = &inputs.colors[g * c..(g + 1) * c];
            let (opacity, mx) = (L::splat(s.opacity), L::splat(s.mx));
            let [mut acc_s1, mut acc_s2, mut acc_dy_s1, mut acc_dy_s0, mut acc_dy2_s0, mut acc_o] = [zero; 6];
            scratch.acc_color.fill(zero);
            for r in (r0..r1).rev() {
                let t = scratch.rec_t[r];
                let (slot, bits) = scratch.rec_meta[r];
                let slot = slot as usize;
                let (row, ch) = (slot / CHUNKS_PER_ROW, slot % CHUNKS_PER_ROW);
                let (dy, _, _) = row_terms(s, y0 + row);
                let dx = chunk_dx(mx, x0 + ch * WIDTH);
                let (alpha, g_val) = (scratch.rec_alpha[r], scratch.rec_g[r]);
                let m = L::mask_from_bits(bits);
                let mut vc_dot = zero;
                for (k, &col) in color.iter().enumerate() {
                    vc_dot = scratch.v_color[k * SLOTS + slot].mul_add(L::splat(col), vc_dot);
                }
                let big_g = scratch.big_g[slot];
                let d = vc_dot.sub(big_g);
                scratch.big_g[slot] = L::select(m, alpha.mul_add(d, big_g), big_g);
                let wgt = L::select(m, alpha.mul(t), zero);
                for (k, a) in scratch.acc_color.iter_mut().enumerate() {
                    *a = wgt.mul_add(scratch.v_color[k * SLOTS + slot], *a);
                }
                // min(0.99, o·g) passes no gradient where it clamps.
                let unclamped = L::and_not(m, opacity.mul(g_val).gt(L::splat(E::<L>::c(ALPHA_MAX))));
                let v_alpha = L::select(unclamped, t.mul(d), zero);
                acc_o = g_val.mul_add(v_alpha, acc_o);
                let v_sigma = zero.sub(alpha.mul(v_alpha));
                let s1 = dx.mul(v_sigma);
                acc_s1 = acc_s1.add(s1);
                acc_s2 = dx.mul_add(s1, acc_s2);
                let dy_l = L::splat(dy);
                acc_dy_s1 = dy_l.mul_add(s1, acc_dy_s1);
                acc_dy_s0 = dy_l.mul_add(v_sigma, acc_dy_s0);
                acc_dy2_s0 = L::splat(dy * dy).mul_add(v_sigma, acc_dy2_s0);
            }
            let half = E::<L>::c(0.5);
            let (s1, dys0) = (acc_s1.sum(), acc_dy_s0.sum());
            let a = s.half_a + s.half_a;
            let cc = s.half_c + s.half_c;
            let rec = &mut out[k * rec_len..(k + 1) * rec_len];
            rec[0] = a * s1 + s.b * dys0;
            rec[1] = s.b * s1 + cc * dys0;
            rec[2] = half * acc_s2.sum();
            rec[3] = acc_dy_s1.sum();
            rec[4] = half * acc_dy2_s0.sum();
            rec[5] = acc_o.sum();
            for (r, a) in rec[RECORD_HEAD..].iter_mut().zip(&scratch.acc_color) {
                *r = a.sum();
            }
        }
    }
}
