//! Tile compositing, forward. The per-tile state (transmittance, activity, depth limit of
//! 256 pixels) lives in 32 eight-lane slots; each Gaussian visits only the rows of the tile
//! its cut-off ellipse reaches and, per row, only the 8-pixel chunks its x-extent reaches.
//! [`TileState::visit_gaussian`] and [`sample`] are the single source of every compositing decision:
//! the backward replays them.

use std::mem::MaybeUninit;

use rayon::prelude::*;

use super::binning::Binning;
use super::lanes::{Lanes, WIDTH};
use super::{Background, RasterInputs, SplatReal, ALPHA_MAX, ALPHA_MIN, TILE, T_STOP};
use crate::error::Result;
use crate::mat3::map3;
use crate::memory::{assume_written, unwritten};
use crate::Real;
use num_traits::{One, Zero};

/// Eight-lane slots per tile: 16 rows × 2 chunks.
pub(super) const SLOTS: usize = TILE * TILE / WIDTH;
const CHUNKS_PER_ROW: usize = TILE / WIDTH;
/// Pixels added on each side of a row's analytic x-extent.
const X_SLACK: f64 = 0.05;

/// Per-Gaussian constants of the pixel loop, derived from the rasterizer's inputs.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Splat<T> {
    pub mx: T,
    pub my: T,
    pub half_a: T,
    pub b: T,
    pub half_c: T,
    pub opacity: T,
    pub depth: T,
    /// The conic is positive definite, so the extents below bound every sample that can
    /// pass the alpha test; otherwise every pixel of the tile is visited.
    pub bounded: bool,
    /// 2·a·L and a·c − b², with L = ln(255·o) padded: the row at offset dy reaches
    /// dx ∈ (−b·dy ± √(2aL − det·dy²)) / a.
    pub two_a_l: T,
    pub det: T,
    pub inv_a: T,
}

impl<T: Real> Splat<T> {
    pub(super) fn new(inputs: &RasterInputs<T>, g: usize) -> Self {
        let [a, b, c] = map3(|k| inputs.conics[g * 3 + k]);
        let half = T::c(0.5);
        let opacity = inputs.opacities[g];
        let det = a * c - b * b;
        // Padding keeps the skip conservative against rounding in σ; extra pixels visited
        // are rejected by the alpha test itself.
        let l = (opacity / T::c(ALPHA_MIN)).ln();
        let l_pad = l * T::c(1.0 + 1e-4) + T::c(1e-4);
        let bounded = a > T::zero() && det > T::zero() && l_pad.is_finite() && (a / det).is_finite();
        Self {
            mx: inputs.means2d[g * 2],
            my: inputs.means2d[g * 2 + 1],
            half_a: half * a,
            b,
            half_c: half * c,
            opacity,
            depth: inputs.depths[g],
            bounded,
            two_a_l: T::c(2.0) * a * l_pad,
            det,
            inv_a: T::one() / a,
        }
    }
}

/// The row-constant part of σ: dy = my − (y + 0.5), b·dy and ½c·dy², with the same
/// operations as [`row_plan`] (so the same bits).
#[inline(always)]
pub(super) fn row_terms<T: Real>(s: &Splat<T>, y: usize) -> (T, T, T) {
    let dy = s.my - T::c(y as f64 + 0.5);
    (dy, s.b * dy, s.half_c * dy * dy)
}

/// (0, 1, …, 7): lane offsets of pixel coordinates.
#[inline(always)]
fn iota<L: Lanes>() -> L {
    L::from_array(std::array::from_fn(|i| L::Elem::c(i as f64)))
}

/// dx = mx − (x + 0.5) for the eight pixels starting at column `xc` (the pixel centres
/// are exact in floating point, so this is one rounding, as in the scalar formula).
#[inline(always)]
pub(super) fn chunk_dx<L: Lanes>(mx: L, xc: usize) -> L {
    mx.sub(L::splat(L::Elem::c(xc as f64 + 0.5)).add(iota()))
}

/// Which 8-pixel chunks of each tile row a Gaussian can reach (bit r of `chunks[c]` for
/// row r, chunk c), and the row terms of σ, for all 16 rows at once. The row at offset
/// dy reaches dx ∈ (−b·dy ± √(2aL − det·dy²)) / a; a negative discriminant (outside the
/// ellipse's y-extent) yields NaN, which fails both comparisons.
pub(super) struct RowPlan<T> {
    pub chunks: [u16; CHUNKS_PER_ROW],
    pub b_dy: [T; TILE],
    pub half_c_dy2: [T; TILE],
}

#[inline(always)]
pub(super) fn row_plan<L: Lanes>(s: &Splat<L::Elem>, x0: usize, y0: usize) -> RowPlan<L::Elem> {
    type E<L> = <L as Lanes>::Elem;
    let mut plan = RowPlan {
        chunks: [0; CHUNKS_PER_ROW],
        b_dy: [E::<L>::zero(); TILE],
        half_c_dy2: [E::<L>::zero(); TILE],
    };
    let (b, half_c) = (L::splat(s.b), L::splat(s.half_c));
    for part in 0..TILE / WIDTH {
        let r0 = part * WIDTH;
        let dy = L::splat(s.my).sub(L::splat(E::<L>::c((y0 + r0) as f64 + 0.5)).add(iota()));
        let b_dy = b.mul(dy);
        plan.b_dy[r0..r0 + WIDTH].copy_from_slice(&b_dy.to_array());
        plan.half_c_dy2[r0..r0 + WIDTH].copy_from_slice(&half_c.mul(dy).mul(dy).to_array());
        if !s.bounded {
            for bits in &mut plan.chunks {
                *bits |= 0xff << r0;
            }
            continue;
        }
        let disc = L::splat(s.two_a_l).sub(L::splat(s.det).mul(dy).mul(dy));
        let inv_a = L::splat(s.inv_a);
        let half_width = disc.sqrt().mul(inv_a);
        let centre = L::splat(s.mx - E::<L>::c(0.5)).add(b_dy.mul(inv_a));
        // Slack for rounding in σ and in the bound itself (≈1e-4 px for pixel-sized
        // Gaussians, growing with the extent): far below a pixel.
        let padded = half_width.mul_add(L::splat(E::<L>::c(1.0 + 1e-3)), L::splat(E::<L>::c(X_SLACK)));
        let lo = centre.sub(padded);
        let hi = centre.add(padded);
        for (ch, bits) in plan.chunks.iter_mut().enumerate() {
            let xc = x0 + ch * WIDTH;
            let first = L::splat(E::<L>::c(xc as f64));
            let last = L::splat(E::<L>::c((xc + WIDTH - 1) as f64));
            let reach = L::mask_bits(L::and(first.le(hi), last.ge(lo)));
            *bits |= (reach as u16) << r0;
        }
    }
    plan
}

/// One Gaussian at eight pixels: (g = exp(−σ), α = min(0.99, o·g), σ ≥ 0 ∧ α ≥ 1/255).
#[inline(always)]
pub(super) fn sample<L: Lanes>(half_a: L, opacity: L, dx: L, b_dy: L, half_c_dy2: L) -> (L, L, L::Mask) {
    let zero = L::splat(L::Elem::zero());
    let sigma = dx.mul_add(half_a.mul_add(dx, b_dy), half_c_dy2);
    let g = zero.sub(sigma).exp_nonpositive();
    let alpha = L::splat(L::Elem::c(ALPHA_MAX)).min(opacity.mul(g));
    let valid = L::and(sigma.ge(zero), alpha.ge(L::splat(L::Elem::c(ALPHA_MIN))));
    (g, alpha, valid)
}

/// Compositing state of one tile.
#[derive(Clone)]
pub(super) struct TileState<L: Lanes> {
    pub t: [L; SLOTS],
    pub active: [L::Mask; SLOTS],
    pub depth_limit: [L; SLOTS],
    pub row_active: [u32; TILE],
    pub num_active: u32,
    pub x0: usize,
    pub y0: usize,
}

impl<L: Lanes> TileState<L> {
    pub(super) fn new<T: Real>(inputs: &RasterInputs<T>, tile_x: usize, tile_y: usize) -> Self
    where
        L: Lanes<Elem = T>,
    {
        let (x0, y0) = (tile_x * TILE, tile_y * TILE);
        let mut active = [L::mask_from_bits(0); SLOTS];
        let mut depth_limit = [L::splat(T::infinity()); SLOTS];
        let mut row_active = [0u32; TILE];
        let eps = L::splat(inputs.depth_eps);
        for row in 0..TILE {
            let y = y0 + row;
            if y >= inputs.height {
                break; // rows below the image: inactive, no depth limit
            }
            for ch in 0..CHUNKS_PER_ROW {
                let xc = x0 + ch * WIDTH;
                let lanes = WIDTH.min(inputs.width.saturating_sub(xc));
                if lanes == 0 {
                    continue; // a chunk past the image's right edge: inactive
                }
                let bits = (0xffu16 >> (WIDTH - lanes)) as u8; // the chunk's pixels in the image
                let slot = row * CHUNKS_PER_ROW + ch;
                active[slot] = L::mask_from_bits(bits);
                row_active[row] += lanes as u32;
                let Some(d) = inputs.depth_map else { continue };
                // The chunk's depths, ∞ past the image's edge (∞ + ε stays ∞), plus ε.
                let first = y * inputs.width + xc;
                let mut depths = [T::infinity(); WIDTH];
                depths[..lanes].copy_from_slice(&d[first..first + lanes]);
                depth_limit[slot] = L::from_array(depths).add(eps);
            }
        }
        Self {
            t: [L::splat(T::one()); SLOTS],
            active,
            depth_limit,
            num_active: row_active.iter().sum(),
            row_active,
            x0,
            y0,
        }
    }

    /// Composites one Gaussian over the tile, front to back: updates T and the active
    /// pixels, and calls `sink(slot, alpha, g, t_before, contributing)` for every visited
    /// chunk with at least one contributing pixel. Returns the number of chunks sampled.
    #[inline(always)]
    pub(super) fn visit_gaussian(
        &mut self,
        s: &Splat<L::Elem>,
        mut sink: impl FnMut(usize, L, L, L, L::Mask),
    ) -> u32 {
        let mut sampled = 0;
        let one = L::splat(L::Elem::one());
        let t_stop = L::splat(L::Elem::c(T_STOP));
        let (half_a, opacity, mx) = (L::splat(s.half_a), L::splat(s.opacity), L::splat(s.mx));
        let depth = L::splat(s.depth);
        let plan = row_plan::<L>(s, self.x0, self.y0);
        let mut rows = plan.chunks.iter().fold(0u16, |a, b| a | b);
        while rows != 0 {
            let row = rows.trailing_zeros() as usize;
            rows &= rows - 1;
            if self.row_active[row] == 0 {
                continue;
            }
            let (b_dy, half_c_dy2) = (L::splat(plan.b_dy[row]), L::splat(plan.half_c_dy2[row]));
            for ch in 0..CHUNKS_PER_ROW {
                let slot = row * CHUNKS_PER_ROW + ch;
                let act = self.active[slot];
                if plan.chunks[ch] >> row & 1 == 0 || L::mask_bits(act) == 0 {
                    continue;
                }
                let dx = chunk_dx(mx, self.x0 + ch * WIDTH);
                sampled += 1;
                let (g, alpha, valid) = sample(half_a, opacity, dx, b_dy, half_c_dy2);
                let visible = depth.le(self.depth_limit[slot]);
                let m = L::and(L::and(valid, visible), act);
                if L::mask_bits(m) == 0 {
                    continue;
                }
                let t = self.t[slot];
                let next_t = t.mul(one.sub(alpha));
                let stop = L::and_not(m, next_t.ge(t_stop));
                let contrib = L::and_not(m, stop);
                sink(slot, alpha, g, t, contrib);
                self.t[slot] = L::select(contrib, next_t, t);
                let stopped = L::mask_bits(stop);
                if stopped != 0 {
                    self.active[slot] = L::and_not(act, stop);
                    self.row_active[row] -= stopped.count_ones();
                    self.num_active -= stopped.count_ones();
                }
            }
        }
        sampled
    }
}

/// Per-Gaussian pixel-loop constants for every Gaussian (culled ones are never visited).
pub(super) fn splats<T: Real>(inputs: &RasterInputs<T>) -> Vec<Splat<T>> {
    (0..inputs.num_gaussians)
        .into_par_iter()
        .with_min_len(1024)
        .map(|g| Splat::new(inputs, g))
        .collect()
}

/// Outputs of [`rasterize_forward`].
#[derive(Debug, Clone)]
pub struct RasterForward<T> {
    /// `(H, W, C)` composited colour including T·background.
    pub image: Vec<T>,
    /// `(H, W)` transmittance after the last contributing sample.
    pub transmittance: Vec<T>,
    /// Tile lists, reused by [`super::rasterize_backward`].
    pub binning: Binning,
    /// Gaussian-pixel pairs evaluated (8 per sampled chunk), for throughput figures.
    pub evaluated_pairs: u64,
}

/// Renders with the fastest lanes for `T` (AVX2 for f32 when built for x86-64-v3).
pub fn rasterize_forward<T: SplatReal>(inputs: &RasterInputs<T>) -> Result<RasterForward<T>> {
    rasterize_forward_with::<T::Fast>(inputs)
}

/// Renders with the lane implementation `L` (tests compare `Avx2` and `Emu<f32>`).
pub fn rasterize_forward_with<L: Lanes>(inputs: &RasterInputs<L::Elem>) -> Result<RasterForward<L::Elem>>
where
    L::Elem: Real,
{
    inputs.validate()?;
    let binning = Binning::new(inputs)?;
    let splats = splats(inputs);
    let (w, h, c) = (inputs.width, inputs.height, inputs.channels);
    // Every pixel of both is written whole by its tile's `write_tile` below: neither is
    // cleared or filled first (a pass over 4 MB at 512²).
    let mut image = unwritten("splat image (H, W, C)", w * h * c)?;
    let mut transmittance = unwritten("splat transmittance (H, W)", w * h)?;
    let zero_bg = vec![L::Elem::zero(); c];
    let background = inputs.background.unwrap_or(Background::Uniform(&zero_bg));
    let evaluated_chunks: u64 = image
        .par_chunks_mut(TILE * w * c)
        .zip(transmittance.par_chunks_mut(TILE * w))
        // Every row of tiles a task of its own that an idle thread can take. Left to
        // rayon, two threads split the rows into ~4 runs of 8, and a run across the face
        // costs several times one across the background, so one thread waited on the
        // other. Paired, alone: forward −0.36 ms, backward −0.60 ms (faster in 175 and
        // 174 of 200); a 512² frame −1.0 ms (50 of 60), the iteration within its noise.
        // The same for the mesh raster's bands measured −0.1 ms alone and nothing in a
        // frame, so they are left to rayon.
        .with_max_len(1)
        .enumerate()
        .map_init(
            || vec![L::splat(L::Elem::zero()); c * SLOTS],
            |acc, (tile_y, (image_rows, t_rows))| {
                let mut sampled = 0u64;
                for tile_x in 0..binning.tiles_x {
                    let tile = tile_y * binning.tiles_x + tile_x;
                    let list = &binning.tile_gaussians
                        [binning.tile_offsets[tile] as usize..binning.tile_offsets[tile + 1] as usize];
                    let mut st = TileState::<L>::new(inputs, tile_x, tile_y);
                    acc.fill(L::splat(L::Elem::zero()));
                    for &g in list {
                        if st.num_active == 0 {
                            break;
                        }
                        let g = g as usize;
                        let color = &inputs.colors[g * c..(g + 1) * c];
                        sampled += st.visit_gaussian(&splats[g], |slot, alpha, _g, t, contrib| {
                            let wgt = L::select(contrib, alpha.mul(t), L::splat(L::Elem::zero()));
                            for (ch, &col) in color.iter().enumerate() {
                                let a = &mut acc[ch * SLOTS + slot];
                                *a = wgt.mul_add(L::splat(col), *a);
                            }
                        }) as u64;
                    }
                    write_tile(&st, acc, background, image_rows, t_rows, w, h, c);
                }
                sampled
            },
        )
        .sum();
    // SAFETY: the row bands partition both buffers, and each band's tiles wrote every
    // pixel of it (`write_tile`: each pixel lies in exactly one tile's chunk).
    let (image, transmittance) = unsafe { (assume_written(image), assume_written(transmittance)) };
    Ok(RasterForward {
        image,
        transmittance,
        binning,
        evaluated_pairs: evaluated_chunks * WIDTH as u64,
    })
}

/// Writes a finished tile's pixels, each whole: colour = accumulated + T·background, and T.
#[allow(clippy::too_many_arguments)]
fn write_tile<L: Lanes>(
    st: &TileState<L>,
    acc: &[L],
    background: Background<'_, L::Elem>,
    image_rows: &mut [MaybeUninit<L::Elem>],
    t_rows: &mut [MaybeUninit<L::Elem>],
    w: usize,
    h: usize,
    c: usize,
) {
    for row in 0..TILE {
        let y = st.y0 + row;
        if y >= h {
            break;
        }
        for ch in 0..CHUNKS_PER_ROW {
            let xc = st.x0 + ch * WIDTH;
            let lanes = WIDTH.min(w.saturating_sub(xc));
            if lanes == 0 {
                continue; // a chunk past the image's right edge
            }
            let slot = row * CHUNKS_PER_ROW + ch;
            let t = st.t[slot].to_array();
            let first = row * w + xc;
            for (dst, &ti) in t_rows[first..first + lanes].iter_mut().zip(&t) {
                dst.write(ti);
            }
            // The chunk's pixels and (for an image) what lies behind them, sliced once, so
            // the strided per-channel loops below run without bounds checks. With the
            // buffers no longer cleared first: a 512² frame's splat −0.10 ms of 5.2
            // (faster in 168 of 200); the write over the mesh image is ~0.6 ms of it.
            let pixels = &mut image_rows[first * c..(first + lanes) * c];
            match background {
                Background::Uniform(colour) => {
                    for (k, &behind) in colour.iter().enumerate() {
                        let col = acc[k * SLOTS + slot].to_array();
                        let dst = pixels[k..].iter_mut().step_by(c);
                        for ((d, &ci), &ti) in dst.zip(&col).zip(&t) {
                            d.write(ci + ti * behind);
                        }
                    }
                }
                Background::Image { values, channels } => {
                    let start = (y * w + xc) * channels;
                    let behind = &values[start..start + lanes * channels];
                    for k in 0..c {
                        let col = acc[k * SLOTS + slot].to_array();
                        let dst = pixels[k..].iter_mut().step_by(c);
                        let src = behind[k..].iter().step_by(channels);
                        for (((d, &b), &ci), &ti) in dst.zip(src).zip(&col).zip(&t) {
                            d.write(ci + ti * b);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::lanes::Emu;
    use crate::splat::project_forward;
    use crate::splat::synthetic::SyntheticSplat;

    /// A tile's state before any Gaussian: exactly its pixels inside the image active, each
    /// with its mesh depth plus the tolerance as its limit (∞ outside), in interior, edge
    /// and corner tiles of an image that is not a multiple of the tile.
    #[test]
    fn tile_state_starts_from_the_pixels_in_the_image_and_their_depths() {
        fn check<L: Lanes<Elem = f32>>() {
            // A 37 × 37 image (2 tiles + 5 pixels each way), every pixel's depth distinct.
            let size = 37usize;
            let s = SyntheticSplat::<f32>::head(10, size as u32, 0.75, 1);
            let proj = project_forward(&s.camera, &s.inputs(Some(3))).unwrap();
            let depth: Vec<f32> = (0..size * size).map(|i| 0.5 + i as f32 * 1e-3).collect();
            let eps = 0.01f32;
            let inputs = s.raster_inputs(&proj, None, Some(&depth), eps);
            for (tile_x, tile_y) in [(0, 0), (2, 0), (0, 2), (2, 2)] {
                let st = TileState::<L>::new(&inputs, tile_x, tile_y);
                let mut in_image = 0;
                for row in 0..TILE {
                    for ch in 0..CHUNKS_PER_ROW {
                        let slot = row * CHUNKS_PER_ROW + ch;
                        let limits = st.depth_limit[slot].to_array();
                        for (i, &limit) in limits.iter().enumerate() {
                            let (x, y) = (tile_x * TILE + ch * WIDTH + i, tile_y * TILE + row);
                            let inside = x < size && y < size;
                            assert_eq!(L::mask_bits(st.active[slot]) >> i & 1 == 1, inside);
                            let expected = if inside {
                                depth[y * size + x] + eps
                            } else {
                                f32::INFINITY
                            };
                            assert_eq!(limit.to_bits(), expected.to_bits(), "pixel ({x}, {y})");
                            in_image += usize::from(inside);
                        }
                    }
                }
                assert_eq!(st.num_active as usize, in_image);
                assert_eq!(st.row_active.iter().sum::<u32>(), st.num_active);
            }
        }
        check::<Emu<f32>>();
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
        check::<crate::splat::lanes::Avx2>();
    }

    /// Every pixel is written whole by its tile. At a size that is not a multiple of the
    /// tile, a render over a uniform colour and one over an image of that colour (4
    /// channels, the 4th not read) agree bit for bit, and nothing is left unwritten (the
    /// unit tests' fresh buffers read as NaN).
    #[test]
    fn every_pixel_is_written_over_either_background() {
        // 37 = 2 tiles + 5 pixels: the last tile has a partial chunk and one wholly past
        // the image's edge.
        let size = 37;
        let s = SyntheticSplat::<f32>::head(300, size, 0.75, 5);
        let proj = project_forward(&s.camera, &s.inputs(Some(3))).unwrap();
        let colour = [0.2f32, 0.5, 0.9];
        let uniform = rasterize_forward(&s.raster_inputs(&proj, Some(&colour), None, 0.01)).unwrap();
        let values: Vec<f32> = (0..size * size).flat_map(|_| [0.2, 0.5, 0.9, 7.0]).collect();
        let mut inputs = s.raster_inputs(&proj, None, None, 0.01);
        inputs.background = Some(Background::Image {
            values: &values,
            channels: 4,
        });
        let over_image = rasterize_forward(&inputs).unwrap();
        let t = &uniform.transmittance;
        assert!(uniform.image.iter().chain(t).all(|v| v.is_finite()));
        assert!(t.iter().any(|&v| v < 0.5) && t.contains(&1.0));
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&uniform.image), bits(&over_image.image));
        assert_eq!(bits(t), bits(&over_image.transmittance));
        // A mesh depth behind every Gaussian hides none of them: the same render, with the
        // tiles' depth limits read from the map.
        let far = vec![100.0f32; (size * size) as usize];
        let behind_all = rasterize_forward(&s.raster_inputs(&proj, Some(&colour), Some(&far), 0.01)).unwrap();
        assert_eq!(bits(&uniform.image), bits(&behind_all.image));
        assert_eq!(bits(t), bits(&behind_all.transmittance));
    }
}
