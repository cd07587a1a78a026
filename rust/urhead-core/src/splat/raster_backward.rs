//! Tile compositing, backward.
//!
//! Per tile: (1) replay the forward front to back with the same
//! [`TileState::visit_gaussian`], recording for every contributing chunk its T before the
//! sample (recomputed, never divided out), g = exp(−σ) and its contributing lanes; (2) walk them back to front with the scalar recurrence
//! G_{i−1} = α_i·(v_C·c_i) + (1 − α_i)·G_i, G_last = v_C·bg + v_T, so
//! ∂L/∂α_i = T_i·(v_C·c_i − G_i); per (Gaussian, tile) the lane sums become one gradient
//! record at that intersection. (3) Each Gaussian sums its records in its fixed row-major
//! tile order. Replays of long tile lists go segment by segment from snapshots, which
//! bounds the scratch memory.

use rayon::prelude::*;

use super::binning::Binning;
use super::lanes::{Lanes, WIDTH};
use super::raster::{chunk_dx, row_terms, splats, Splat, TileState, SLOTS};
use super::records::{record_gaussian, RowRecords};
use super::{Background, RasterInputs, SplatReal, ALPHA_MAX, TILE};
use crate::composite::behind_gradients;
use crate::error::{check_len, Error, Result};
use crate::memory::zeroed;
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
    /// `(H, W, S)` for an image background: `T·v_image` on its first C channels, zero past
    /// them. `None` for a uniform background or none (its gradient, a sum over the image,
    /// is the caller's).
    pub v_background: Option<Vec<T>>,
}

/// Per-thread scratch of the tile backward.
struct Scratch<L: Lanes> {
    recs: RowRecords<L::Elem>,
    snapshots: Vec<TileState<L>>,
    v_color: Vec<L>,
    big_g: [L; SLOTS],
    acc_color: Vec<L>,
}

/// Adjoint of [`super::rasterize_forward`] (same inputs, its binning) with the fastest
/// lanes for `T`.
/// `transmittance (H, W)`, the forward's, is needed only with an image background (for its
/// gradient).
pub fn rasterize_backward<T: SplatReal>(
    inputs: &RasterInputs<T>,
    binning: &Binning,
    v_image: Option<&[T]>,
    v_transmittance: Option<&[T]>,
    transmittance: Option<&[T]>,
) -> Result<RasterGrads<T>> {
    rasterize_backward_with::<T::Fast>(inputs, binning, v_image, v_transmittance, transmittance)
}

pub fn rasterize_backward_with<L: Lanes>(
    inputs: &RasterInputs<L::Elem>,
    binning: &Binning,
    v_image: Option<&[L::Elem]>,
    v_transmittance: Option<&[L::Elem]>,
    transmittance: Option<&[L::Elem]>,
) -> Result<RasterGrads<L::Elem>> {
    backward_segmented::<L>(inputs, binning, v_image, v_transmittance, transmittance, SEGMENT)
}

/// [`rasterize_backward_with`] replaying tile lists `segment` Gaussians at a time.
fn backward_segmented<L: Lanes>(
    inputs: &RasterInputs<L::Elem>,
    binning: &Binning,
    v_image: Option<&[L::Elem]>,
    v_transmittance: Option<&[L::Elem]>,
    transmittance: Option<&[L::Elem]>,
    segment: usize,
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
    let mut records = zeroed("splat gradient records", binning.num_intersections() * rec_len)?;
    let zero_bg = vec![L::Elem::zero(); c];
    // An image behind: its gradient and its part of each pixel's G_last (v_C·behind) come
    // from one streaming pass first (`behind_gradients`, as for `composite`), and the tiles
    // then run as over black. Read per pixel inside the tiles' replay instead, the
    // backward took 2.5 ms more, more than a composite's whole backward.
    let folded: Vec<L::Elem>;
    let (background, v_transmittance, v_background) = match inputs.background {
        Some(Background::Image { values, channels }) => {
            let t = transmittance.ok_or_else(|| Error::Invalid {
                arg: "transmittance",
                reason: "the forward's (H, W) transmittance is needed with an image background".into(),
            })?;
            check_len("transmittance", t, w * h, &format!("(H, W) = ({h}, {w})"))?;
            match v_image {
                Some(v) => {
                    let g = behind_gradients(t, values, channels, v, c, v_transmittance, true, true)?;
                    folded = g.v_transmittance.expect("asked for");
                    (&zero_bg[..], Some(&folded[..]), g.v_back)
                }
                None => (
                    &zero_bg[..],
                    v_transmittance,
                    Some(zeroed("splat background gradient (H, W, S)", w * h * channels)?),
                ),
            }
        }
        Some(Background::Uniform(colour)) => (colour, v_transmittance, None),
        None => (&zero_bg[..], v_transmittance, None),
    };

    // One task per row of tiles (each its own, as in the forward: their costs are uneven);
    // its records are a contiguous range of intersections.
    let mut row_records: Vec<&mut [L::Elem]> = Vec::with_capacity(binning.tiles_y);
    let mut rest = records.as_mut_slice();
    for ty in 0..binning.tiles_y {
        let lo = binning.tile_offsets[ty * binning.tiles_x] as usize;
        let hi = binning.tile_offsets[(ty + 1) * binning.tiles_x] as usize;
        let (mine, tail) = rest.split_at_mut((hi - lo) * rec_len);
        row_records.push(mine);
        rest = tail;
    }
    row_records
        .into_par_iter()
        .with_max_len(1)
        .enumerate()
        .for_each_init(
            || Scratch::<L> {
                recs: RowRecords::default(),
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
                    let tile = Tile {
                        inputs,
                        splats: &splats,
                        list: &binning.tile_gaussians[lo..hi],
                        x0: tile_x * TILE,
                        y0: tile_y * TILE,
                    };
                    init_upstream(&tile, background, v_image, v_transmittance, scratch);
                    replay_and_accumulate(&tile, tile_x, tile_y, segment, scratch, tile_out);
                }
            },
        );

    // Per Gaussian, sum its intersection records in its fixed (row-major tile) order.
    let mut v_means2d = vec![L::Elem::zero(); n * 2];
    let mut v_conics = vec![L::Elem::zero(); n * 3];
    let mut v_colors = zeroed("colour gradient (N, C)", n * c)?;
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
        v_background,
    })
}

/// One tile's inputs.
struct Tile<'a, T> {
    inputs: &'a RasterInputs<'a, T>,
    splats: &'a [Splat<T>],
    list: &'a [u32],
    x0: usize,
    y0: usize,
}

/// Per-pixel upstream gradients of the tile and G_last = v_C·bg + v_T.
fn init_upstream<L: Lanes>(
    tile: &Tile<L::Elem>,
    background: &[L::Elem],
    v_image: Option<&[L::Elem]>,
    v_transmittance: Option<&[L::Elem]>,
    scratch: &mut Scratch<L>,
) {
    type E<L> = <L as Lanes>::Elem;
    let (w, h, c) = (tile.inputs.width, tile.inputs.height, tile.inputs.channels);
    for slot in 0..SLOTS {
        let (row, ch) = (slot / CHUNKS_PER_ROW, slot % CHUNKS_PER_ROW);
        let y = tile.y0 + row;
        let xc = tile.x0 + ch * WIDTH;
        let lanes = if y < h { WIDTH.min(w.saturating_sub(xc)) } else { 0 };
        let mut g_last = [E::<L>::zero(); WIDTH];
        for k in 0..c {
            let mut vc = [E::<L>::zero(); WIDTH];
            if let Some(g) = v_image {
                for i in 0..lanes {
                    vc[i] = g[(y * w + xc + i) * c + k];
                    g_last[i] += vc[i] * background[k];
                }
            }
            scratch.v_color[k * SLOTS + slot] = L::from_array(vc);
        }
        if let Some(g) = v_transmittance {
            for i in 0..lanes {
                g_last[i] += g[y * w + xc + i];
            }
        }
        scratch.big_g[slot] = L::from_array(g_last);
    }
}

/// Replays the tile's forward (in segments, from snapshots) and accumulates each segment
/// back to front.
fn replay_and_accumulate<L: Lanes>(
    tile: &Tile<L::Elem>,
    tile_x: usize,
    tile_y: usize,
    segment: usize,
    scratch: &mut Scratch<L>,
    out: &mut [L::Elem],
) {
    let mut st = TileState::<L>::new(tile.inputs, tile_x, tile_y);
    scratch.snapshots.clear();
    let mut end = 0;
    while end < tile.list.len() && st.num_active > 0 {
        if end % segment == 0 {
            scratch.snapshots.push(st.clone());
            scratch.recs.clear();
        }
        record_gaussian(&mut st, &tile.splats[tile.list[end] as usize], &mut scratch.recs);
        end += 1;
    }
    let num_segments = scratch.snapshots.len();
    for seg in (0..num_segments).rev() {
        let k0 = seg * segment;
        let k1 = (k0 + segment).min(end);
        if seg + 1 != num_segments {
            let mut replay_state = scratch.snapshots[seg].clone();
            scratch.recs.clear();
            for &g in &tile.list[k0..k1] {
                record_gaussian(&mut replay_state, &tile.splats[g as usize], &mut scratch.recs);
            }
        }
        let recs = std::mem::take(&mut scratch.recs);
        accumulate(tile, k0, k1, &recs, scratch, out);
        scratch.recs = recs;
    }
}

/// Back to front over Gaussians `list[k0..k1)` whose records are `recs.range(k − k0)`:
/// updates G per pixel and writes each Gaussian's gradient record.
fn accumulate<L: Lanes>(
    tile: &Tile<L::Elem>,
    k0: usize,
    k1: usize,
    recs: &RowRecords<L::Elem>,
    scratch: &mut Scratch<L>,
    out: &mut [L::Elem],
) {
    type E<L> = <L as Lanes>::Elem;
    let c = tile.inputs.channels;
    let rec_len = RECORD_HEAD + c;
    let zero = L::splat(E::<L>::zero());
    let alpha_max = L::splat(E::<L>::c(ALPHA_MAX));
    for k in (k0..k1).rev() {
        let range = recs.range(k - k0);
        if range.is_empty() {
            continue;
        }
        let g = tile.list[k] as usize;
        let s = &tile.splats[g];
        let color = &tile.inputs.colors[g * c..(g + 1) * c];
        let (opacity, mx) = (L::splat(s.opacity), L::splat(s.mx));
        let [mut acc_s1, mut acc_s2, mut acc_dy_s1, mut acc_dy_s0, mut acc_dy2_s0, mut acc_o] = [zero; 6];
        scratch.acc_color.fill(zero);
        for r in range.rev() {
            let (t, g_val, slot, bits) = recs.get::<L>(r);
            let (row, ch) = (slot / CHUNKS_PER_ROW, slot % CHUNKS_PER_ROW);
            let (dy, _, _) = row_terms(s, tile.y0 + row);
            let dx = chunk_dx(mx, tile.x0 + ch * WIDTH);
            // α exactly as the forward computed it from g.
            let og = opacity.mul(g_val);
            let alpha = alpha_max.min(og);
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
            let unclamped = L::and_not(m, og.gt(alpha_max));
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::lanes::Emu;
    use crate::splat::{project_forward, rasterize_forward_with, SyntheticSplat};
    use crate::testing::Rng;

    /// Replaying from snapshots in segments gives the same bits as one segment per tile.
    #[test]
    fn segmented_replay_is_bitwise_identical() {
        let mut s = SyntheticSplat::<f32>::head(600, 48, 0.75, 21);
        for v in &mut s.scales {
            *v *= 6.0;
        }
        let proj = project_forward(&s.camera, &s.inputs(Some(3))).unwrap();
        let raster = s.raster_inputs(&proj, None, None, 0.01);
        let fwd = rasterize_forward_with::<Emu<f32>>(&raster).unwrap();
        let mut rng = Rng::new(3);
        let v_image = rng.vec::<f32>(48 * 48 * 3, -1.0, 1.0);
        let run = |segment| {
            backward_segmented::<Emu<f32>>(&raster, &fwd.binning, Some(&v_image), None, None, segment)
                .unwrap()
        };
        let whole = run(usize::MAX);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for segment in [1, 7, 64] {
            let seg = run(segment);
            assert_eq!(bits(&seg.v_means2d), bits(&whole.v_means2d));
            assert_eq!(bits(&seg.v_conics), bits(&whole.v_conics));
            assert_eq!(bits(&seg.v_colors), bits(&whole.v_colors));
            assert_eq!(bits(&seg.v_opacities), bits(&whole.v_opacities));
        }
        assert!(whole.v_means2d.iter().any(|&v| v != 0.0));
    }
}
