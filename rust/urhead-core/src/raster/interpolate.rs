//! `interpolate`: per-vertex attributes → per-pixel attributes through the rasterizer's
//! barycentrics, `out = (1 − b1 − b2)·a0 + b1·a1 + b2·a2` (0 where no triangle), and its
//! adjoint with respect to the attributes and the barycentrics. Either over the whole
//! image or at a list of pixels only (the covered ones, say), which skips the full-image
//! output and, in the adjoint, the full-image output gradient.

use std::ops::Range;

use rayon::prelude::*;

use super::runs::{merge_runs, TriangleRuns};
use super::{check_faces, check_tri_id, TILE_ROWS};
use crate::error::{check_finite, check_indices, check_len, Error, Result};
use crate::memory::{assume_written, unwritten, write_zeros, zeroed};
use crate::Real;

/// Gradients of [`interpolate_backward`]; a field is `Some` exactly when it was asked for.
#[derive(Debug, Clone, Default)]
pub struct InterpolateGrads<T> {
    /// `(V, C)`
    pub v_attr: Option<Vec<T>>,
    /// `(H, W, 2)`
    pub v_bary: Option<Vec<T>>,
}

/// The pixels a pass visits, entry by entry: the whole image or a list. Each pass is
/// compiled for both kinds, so the whole image pays nothing for the list.
trait Sites: Copy + Send + Sync {
    /// The number of entries.
    fn len(self) -> usize;

    /// The flat pixel index `y·W + x` of `entry`.
    fn pixel(self, entry: usize) -> usize;

    /// Whether the pixels never decrease from one entry to the next.
    fn increasing(self) -> bool;

    /// The entries whose pixels lie in `pixels`; for increasing sites only.
    fn entries_in(self, pixels: Range<usize>) -> Range<usize>;

    /// Consecutive entry ranges for the attribute gradient's parallel pass, cut only where
    /// the entries' pixels move to another tile of `tile_len` pixels, and each at least
    /// `tile_len` entries long (bar the last). The image is thus cut into its tiles, and an
    /// increasing list sums its runs tile by tile like the image.
    fn blocks(self, tile_len: usize) -> Vec<Range<usize>>;
}

/// The whole image of `n` pixels, row-major: entry `i` is pixel `i`.
#[derive(Clone, Copy)]
struct WholeImage(usize);

impl Sites for WholeImage {
    fn len(self) -> usize {
        self.0
    }

    #[inline(always)]
    fn pixel(self, entry: usize) -> usize {
        entry
    }

    fn increasing(self) -> bool {
        true
    }

    fn entries_in(self, pixels: Range<usize>) -> Range<usize> {
        pixels
    }

    fn blocks(self, tile_len: usize) -> Vec<Range<usize>> {
        (0..self.0)
            .step_by(tile_len)
            .map(|start| start..(start + tile_len).min(self.0))
            .collect()
    }
}

/// A list of flat pixel indices, checked to lie in the image: any order, repeats allowed.
#[derive(Clone, Copy)]
struct PixelList<'a> {
    pixels: &'a [i64],
    increasing: bool,
}

impl Sites for PixelList<'_> {
    fn len(self) -> usize {
        self.pixels.len()
    }

    #[inline(always)]
    fn pixel(self, entry: usize) -> usize {
        self.pixels[entry] as usize
    }

    fn increasing(self) -> bool {
        self.increasing
    }

    fn entries_in(self, pixels: Range<usize>) -> Range<usize> {
        let first = self.pixels.partition_point(|&p| (p as usize) < pixels.start);
        let end = self.pixels.partition_point(|&p| (p as usize) < pixels.end);
        first..end
    }

    fn blocks(self, tile_len: usize) -> Vec<Range<usize>> {
        let mut blocks = Vec::new();
        let (mut start, mut tile) = (0, 0..0);
        for (entry, &p) in self.pixels.iter().enumerate() {
            let p = p as usize;
            if !tile.contains(&p) {
                if entry - start >= tile_len {
                    blocks.push(start..entry);
                    start = entry;
                }
                tile = tile_of(p, tile_len);
            }
        }
        if start < self.pixels.len() {
            blocks.push(start..self.pixels.len());
        }
        blocks
    }
}

/// The attribute width `C`: a constant for the widths the renderer interpolates (UVs 2,
/// colours and normals 3, rotations 9), so a pixel's loops over its channels unroll, or
/// any width. Like [`Sites`], each pass is compiled for each kind.
trait Channels: Copy + Send + Sync {
    fn get(self) -> usize;
}

#[derive(Clone, Copy)]
struct Fixed<const C: usize>;

impl<const C: usize> Channels for Fixed<C> {
    #[inline(always)]
    fn get(self) -> usize {
        C
    }
}

#[derive(Clone, Copy)]
struct AnyWidth(usize);

impl Channels for AnyWidth {
    #[inline(always)]
    fn get(self) -> usize {
        self.0
    }
}

/// `$body` with `$k` the [`Channels`] of width `$c`.
macro_rules! by_width {
    ($c:expr, $k:ident => $body:expr) => {
        match $c {
            2 => {
                let $k = Fixed::<2>;
                $body
            }
            3 => {
                let $k = Fixed::<3>;
                $body
            }
            9 => {
                let $k = Fixed::<9>;
                $body
            }
            c => {
                let $k = AnyWidth(c);
                $body
            }
        }
    };
}

/// The pixels of the tile holding `pixel`.
fn tile_of(pixel: usize, tile_len: usize) -> Range<usize> {
    let first = pixel - pixel % tile_len;
    first..first + tile_len
}

fn list(pixels: &[i64]) -> PixelList<'_> {
    PixelList {
        pixels,
        increasing: pixels.is_sorted(),
    }
}

/// Validated inputs shared by both passes.
struct Inputs<'a, T> {
    attr: &'a [T],
    faces: &'a [i32],
    tri_id: &'a [i32],
    bary: &'a [T],
    height: usize,
    width: usize,
}

impl<'a, T: Real> Inputs<'a, T> {
    fn new(
        attr: &'a [T],
        channels: usize,
        faces: &'a [i32],
        tri_id: &'a [i32],
        bary: &'a [T],
        height: usize,
        width: usize,
        pixels: Option<&[i64]>,
    ) -> Result<Self> {
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
        if let Some(pixels) = pixels {
            check_indices("pixels", pixels, 0, (height * width) as i64)?;
        }
        check_finite("attr", attr)?;
        check_finite("bary", bary)?;
        Ok(Self {
            attr,
            faces,
            tri_id,
            bary,
            height,
            width,
        })
    }

    /// Pixels per screen tile, and entries per parallel chunk.
    fn tile_len(&self) -> usize {
        TILE_ROWS * self.width
    }

    /// The attribute rows of triangle `tri`'s three vertices.
    #[inline(always)]
    fn corners<K: Channels>(&self, tri: i32, width: K) -> [&[T]; 3] {
        let c = width.get();
        let row = |k: usize| {
            let v = self.faces[3 * tri as usize + k] as usize;
            &self.attr[v * c..(v + 1) * c]
        };
        [row(0), row(1), row(2)]
    }

    fn forward<S: Sites, K: Channels>(&self, sites: S, width: K) -> Result<Vec<T>> {
        let c = width.get();
        let mut out = unwritten("interpolated values", sites.len() * c)?;
        out.par_chunks_mut(self.tile_len() * c)
            .enumerate()
            .for_each(|(chunk, out)| {
                let first = chunk * self.tile_len();
                for (i, px) in out.chunks_exact_mut(c).enumerate() {
                    let idx = sites.pixel(first + i);
                    let tri = self.tri_id[idx];
                    if tri < 0 {
                        write_zeros(px);
                        continue;
                    }
                    let (b1, b2) = (self.bary[2 * idx], self.bary[2 * idx + 1]);
                    let b0 = T::one() - b1 - b2;
                    let [a0, a1, a2] = self.corners(tri, width);
                    for k in 0..c {
                        px[k].write(b0 * a0[k] + b1 * a1[k] + b2 * a2[k]);
                    }
                }
            });
        // SAFETY: the chunks partition the sites' rows, and each row was written whole
        // (zeros off the mesh).
        Ok(unsafe { assume_written(out) })
    }

    fn backward<S: Sites, K: Channels>(
        &self,
        sites: S,
        width: K,
        v_out: &[T],
        need_attr: bool,
        need_bary: bool,
    ) -> Result<InterpolateGrads<T>> {
        Ok(InterpolateGrads {
            v_attr: need_attr.then(|| self.attr_grad(sites, width, v_out)),
            v_bary: need_bary
                .then(|| self.bary_grad(sites, width, v_out))
                .transpose()?,
        })
    }

    /// `(V, C)`: per block, runs of consecutive entries on one triangle (a run also ends
    /// where the pixels move to another tile), merged in block order.
    fn attr_grad<S: Sites, K: Channels>(&self, sites: S, width: K, v_out: &[T]) -> Vec<T> {
        let (c, tile_len) = (width.get(), self.tile_len());
        // A task per block, as the rasterizer's backward (−0.15 ms, faster in 147 of 150,
        // the skinning rotations' backward at a real step alone).
        let runs: Vec<TriangleRuns<T>> = sites
            .blocks(tile_len)
            .into_par_iter()
            .with_max_len(1)
            .map(|block| {
                let mut runs = TriangleRuns::new(3 * c);
                let mut run_tile = 0..0;
                for entry in block {
                    let idx = sites.pixel(entry);
                    let tri = self.tri_id[idx];
                    if tri < 0 {
                        continue;
                    }
                    let (b1, b2) = (self.bary[2 * idx], self.bary[2 * idx + 1]);
                    let b = [T::one() - b1 - b2, b1, b2];
                    let slot = if run_tile.contains(&idx) {
                        runs.slot(tri as u32)
                    } else {
                        run_tile = tile_of(idx, tile_len);
                        runs.new_slot(tri as u32)
                    };
                    let g = &v_out[entry * c..(entry + 1) * c];
                    for k in 0..3 {
                        for (acc, gk) in slot[k * c..(k + 1) * c].iter_mut().zip(g) {
                            *acc += b[k] * *gk;
                        }
                    }
                }
                runs
            })
            .collect();
        let per_tri = merge_runs(&runs, self.faces.len() / 3, 3 * c);
        let mut v_attr = vec![T::zero(); self.attr.len()];
        for (f, sums) in self.faces.chunks_exact(3).zip(per_tri.chunks_exact(3 * c)) {
            for k in 0..3 {
                let dst = &mut v_attr[f[k] as usize * c..(f[k] as usize + 1) * c];
                for (a, s) in dst.iter_mut().zip(&sums[k * c..(k + 1) * c]) {
                    *a += *s;
                }
            }
        }
        v_attr
    }

    /// `(H, W, 2)`, each pixel summing its entries in entry order: per tile in parallel
    /// when the sites are increasing, else in one serial pass.
    fn bary_grad<S: Sites, K: Channels>(&self, sites: S, width: K, v_out: &[T]) -> Result<Vec<T>> {
        let mut v_bary = zeroed("barycentric gradient", self.height * self.width * 2)?;
        let tile_len = self.tile_len();
        if sites.increasing() {
            v_bary
                .par_chunks_mut(tile_len * 2)
                .enumerate()
                .for_each(|(tile, vb)| {
                    let first = tile * tile_len;
                    for entry in sites.entries_in(first..first + vb.len() / 2) {
                        self.add_bary_grad(sites, width, entry, v_out, first, vb);
                    }
                });
        } else {
            for entry in 0..sites.len() {
                self.add_bary_grad(sites, width, entry, v_out, 0, &mut v_bary);
            }
        }
        Ok(v_bary)
    }

    /// Adds `entry`'s barycentric gradient to `v_bary`, the image from pixel `first_pixel`.
    #[inline(always)]
    fn add_bary_grad<S: Sites, K: Channels>(
        &self,
        sites: S,
        width: K,
        entry: usize,
        v_out: &[T],
        first_pixel: usize,
        v_bary: &mut [T],
    ) {
        let idx = sites.pixel(entry);
        let tri = self.tri_id[idx];
        if tri < 0 {
            return;
        }
        let c = width.get();
        let [a0, a1, a2] = self.corners(tri, width);
        let g = &v_out[entry * c..(entry + 1) * c];
        let (mut d1, mut d2) = (T::zero(), T::zero());
        for k in 0..c {
            d1 += g[k] * (a1[k] - a0[k]);
            d2 += g[k] * (a2[k] - a0[k]);
        }
        let vb = &mut v_bary[2 * (idx - first_pixel)..2 * (idx - first_pixel) + 2];
        vb[0] += d1;
        vb[1] += d2;
    }
}

/// `attr (V, C)`, `faces (F, 3)` indexing `attr` (e.g. UV faces for UV coordinates),
/// `tri_id (H, W)` and `bary (H, W, 2)` from the rasterizer → `(H, W, C)`, or `(P, C)` at
/// `pixels (P,)` (flat indices `y·W + x`, any order, repeats allowed) when given. The
/// values are those of the whole image at the same pixels, bit for bit.
pub fn interpolate_forward<T: Real>(
    attr: &[T],
    channels: usize,
    faces: &[i32],
    tri_id: &[i32],
    bary: &[T],
    height: usize,
    width: usize,
    pixels: Option<&[i64]>,
) -> Result<Vec<T>> {
    let inputs = Inputs::new(attr, channels, faces, tri_id, bary, height, width, pixels)?;
    by_width!(channels, k => match pixels {
        None => inputs.forward(WholeImage(height * width), k),
        Some(pixels) => inputs.forward(list(pixels), k),
    })
}

/// Adjoint of [`interpolate_forward`] given `v_out`, `(H, W, C)`, or `(P, C)` with
/// `pixels`; computes the gradients flagged in `need_attr` / `need_bary` only. `v_bary` is
/// always `(H, W, 2)`, zero at pixels not listed; a repeated pixel receives the sum of its
/// entries' gradients, in list order. The attribute gradient is accumulated per run of
/// consecutive pixels on one triangle (runs end at tile boundaries), merged in a fixed
/// order: deterministic for any thread count, and for a list holding every covered pixel
/// in increasing order the same, bit for bit, as the whole image's. A list in increasing
/// order is also the fast one (others sum `v_bary` serially).
pub fn interpolate_backward<T: Real>(
    attr: &[T],
    channels: usize,
    faces: &[i32],
    tri_id: &[i32],
    bary: &[T],
    height: usize,
    width: usize,
    pixels: Option<&[i64]>,
    v_out: &[T],
    need_attr: bool,
    need_bary: bool,
) -> Result<InterpolateGrads<T>> {
    let inputs = Inputs::new(attr, channels, faces, tri_id, bary, height, width, pixels)?;
    let (c, h, w) = (channels, height, width);
    match pixels {
        None => {
            check_len("v_out", v_out, h * w * c, &format!("(H, W, C) = ({h}, {w}, {c})"))?;
            by_width!(c, k => inputs.backward(WholeImage(h * w), k, v_out, need_attr, need_bary))
        }
        Some(pixels) => {
            let p = pixels.len();
            check_len("v_out", v_out, p * c, &format!("(P, C) = ({p}, {c})"))?;
            by_width!(c, k => inputs.backward(list(pixels), k, v_out, need_attr, need_bary))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{on_threads, Rng};

    const H: usize = 37;
    const W: usize = 29;
    const C: usize = 3;

    /// Random attributes and faces over a coherent triangle-id image: patches of a few
    /// pixels per triangle, some empty pixels, and rows 6..10 on one triangle, so that runs
    /// cross the tile boundary at row 8.
    struct Scene<T> {
        attr: Vec<T>,
        faces: Vec<i32>,
        tri_id: Vec<i32>,
        bary: Vec<T>,
    }

    fn scene<T: Real>(seed: u64) -> Scene<T> {
        let (num_verts, num_faces) = (40, 50);
        let mut rng = Rng::new(seed);
        let faces = (0..3 * num_faces)
            .map(|_| (rng.next_u64() % num_verts as u64) as i32)
            .collect();
        let tri_id = (0..H * W)
            .map(|i| {
                let (y, x) = (i / W, i % W);
                if (6..10).contains(&y) {
                    return 0;
                }
                let t = (x / 4 + 7 * (y / 3)) as i32 % (num_faces + 3) - 3;
                t.max(-1)
            })
            .collect::<Vec<_>>();
        let mut bary = vec![T::zero(); H * W * 2];
        for (b, &t) in bary.chunks_exact_mut(2).zip(&tri_id) {
            if t >= 0 {
                let b1 = rng.uniform(0.0, 1.0);
                b[0] = T::c(b1);
                b[1] = T::c(rng.uniform(0.0, 1.0 - b1));
            }
        }
        Scene {
            attr: rng.vec(num_verts * C, -1.0, 1.0),
            faces,
            tri_id,
            bary,
        }
    }

    /// `n` pixels drawn at random: any order, repeats, empty pixels.
    fn random_pixels(n: usize, seed: u64) -> Vec<i64> {
        let mut rng = Rng::new(seed);
        (0..n).map(|_| (rng.next_u64() % (H * W) as u64) as i64).collect()
    }

    fn forward<T: Real>(s: &Scene<T>, pixels: Option<&[i64]>) -> Result<Vec<T>> {
        interpolate_forward(&s.attr, C, &s.faces, &s.tri_id, &s.bary, H, W, pixels)
    }

    fn backward<T: Real>(s: &Scene<T>, pixels: Option<&[i64]>, v_out: &[T]) -> Result<InterpolateGrads<T>> {
        interpolate_backward(
            &s.attr, C, &s.faces, &s.tri_id, &s.bary, H, W, pixels, v_out, true, true,
        )
    }

    /// The whole-image output gradient whose restriction to `pixels` is `v_out (P, C)`:
    /// what indexing the image at `pixels` passes back (repeats summed).
    fn scattered<T: Real>(pixels: &[i64], v_out: &[T]) -> Vec<T> {
        let mut image = vec![T::zero(); H * W * C];
        for (&p, g) in pixels.iter().zip(v_out.chunks_exact(C)) {
            for (a, &b) in image[p as usize * C..(p as usize + 1) * C].iter_mut().zip(g) {
                *a += b;
            }
        }
        image
    }

    fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
    }

    /// Every width, the fixed ones (2, 3, 9) and others, against the sums written out per
    /// pixel: values, attribute and barycentric gradients.
    #[test]
    fn every_width_matches_the_plain_sums() {
        let s = scene::<f64>(13);
        let num_verts = s.attr.len() / C;
        for width in [1, 2, 3, 4, 9, 11] {
            let mut rng = Rng::new(14 + width as u64);
            let attr: Vec<f64> = rng.vec(num_verts * width, -1.0, 1.0);
            let v_out: Vec<f64> = rng.vec(H * W * width, -1.0, 1.0);
            let values = interpolate_forward(&attr, width, &s.faces, &s.tri_id, &s.bary, H, W, None).unwrap();
            let grads = interpolate_backward(
                &attr, width, &s.faces, &s.tri_id, &s.bary, H, W, None, &v_out, true, true,
            )
            .unwrap();
            let (mut v_attr, mut v_bary) = (vec![0.0; attr.len()], vec![0.0; H * W * 2]);
            for p in 0..H * W {
                let tri = s.tri_id[p];
                let out = &values[p * width..(p + 1) * width];
                if tri < 0 {
                    assert!(out.iter().all(|&x| x == 0.0));
                    continue;
                }
                let (b1, b2) = (s.bary[2 * p], s.bary[2 * p + 1]);
                let b = [1.0 - b1 - b2, b1, b2];
                let v: Vec<usize> = (0..3).map(|k| s.faces[3 * tri as usize + k] as usize).collect();
                for ch in 0..width {
                    let a = |k: usize| attr[v[k] * width + ch];
                    assert!((out[ch] - (b[0] * a(0) + b[1] * a(1) + b[2] * a(2))).abs() < 1e-12);
                    let g = v_out[p * width + ch];
                    for k in 0..3 {
                        v_attr[v[k] * width + ch] += b[k] * g;
                    }
                    v_bary[2 * p] += g * (a(1) - a(0));
                    v_bary[2 * p + 1] += g * (a(2) - a(0));
                }
            }
            assert!(
                max_abs_diff(grads.v_attr.as_ref().unwrap(), &v_attr) < 1e-12,
                "width {width}"
            );
            assert!(
                max_abs_diff(grads.v_bary.as_ref().unwrap(), &v_bary) < 1e-12,
                "width {width}"
            );
        }
    }

    #[test]
    fn listed_values_are_the_image_values_bit_for_bit() {
        let s = scene::<f32>(1);
        let image = forward(&s, None).unwrap();
        let pixels = random_pixels(700, 2);
        let listed = forward(&s, Some(&pixels)).unwrap();
        assert_eq!(listed.len(), pixels.len() * C);
        for (&p, v) in pixels.iter().zip(listed.chunks_exact(C)) {
            assert_eq!(v, &image[p as usize * C..(p as usize + 1) * C]);
        }
        assert!(
            pixels.iter().any(|&p| s.tri_id[p as usize] < 0),
            "no empty pixel listed"
        );
    }

    #[test]
    fn listed_gradients_are_those_of_the_image_at_the_scattered_output_gradient() {
        let s = scene::<f64>(3);
        let shuffled = random_pixels(900, 4);
        let mut increasing = shuffled.clone();
        increasing.sort();
        let v_out: Vec<f64> = Rng::new(5).vec(shuffled.len() * C, -1.0, 1.0);
        // Repeated pixels sum in another order: equal up to rounding.
        for pixels in [shuffled, increasing] {
            let listed = backward(&s, Some(&pixels), &v_out).unwrap();
            let image = backward(&s, None, &scattered(&pixels, &v_out)).unwrap();
            for (l, i) in [(&listed.v_attr, &image.v_attr), (&listed.v_bary, &image.v_bary)] {
                assert!(max_abs_diff(l.as_ref().unwrap(), i.as_ref().unwrap()) < 1e-12);
            }
        }
    }

    #[test]
    fn every_covered_pixel_in_increasing_order_sums_like_the_image() {
        let s = scene::<f32>(6);
        // Every covered pixel and a few empty ones, as a list in increasing order.
        let pixels: Vec<i64> = (0..(H * W) as i64)
            .filter(|&p| s.tri_id[p as usize] >= 0 || p % 5 == 0)
            .collect();
        let mut image_v_out: Vec<f32> = Rng::new(7).vec(H * W * C, -1.0, 1.0);
        for (p, g) in image_v_out.chunks_exact_mut(C).enumerate() {
            if s.tri_id[p] < 0 {
                g.fill(0.0);
            }
        }
        let v_out: Vec<f32> = pixels
            .iter()
            .flat_map(|&p| image_v_out[p as usize * C..(p as usize + 1) * C].to_vec())
            .collect();
        let listed = backward(&s, Some(&pixels), &v_out).unwrap();
        let image = backward(&s, None, &image_v_out).unwrap();
        assert_eq!(listed.v_attr, image.v_attr);
        assert_eq!(listed.v_bary, image.v_bary);
    }

    #[test]
    fn listed_passes_are_bitwise_identical_for_any_thread_count() {
        let s = scene::<f32>(8);
        let shuffled = random_pixels(3000, 9);
        let mut increasing = shuffled.clone();
        increasing.sort();
        let v_out: Vec<f32> = Rng::new(10).vec(shuffled.len() * C, -1.0, 1.0);
        for pixels in [shuffled, increasing] {
            let run = |threads: usize| {
                on_threads(threads, || {
                    let g = backward(&s, Some(&pixels), &v_out).unwrap();
                    (forward(&s, Some(&pixels)).unwrap(), g.v_attr, g.v_bary)
                })
            };
            let reference = run(1);
            for threads in [2, 3] {
                assert!(run(threads) == reference, "{threads} threads differ from 1");
            }
        }
    }

    #[test]
    fn an_empty_list_gives_no_values_and_zero_gradients() {
        let s = scene::<f64>(11);
        assert!(forward(&s, Some(&[])).unwrap().is_empty());
        let g = backward(&s, Some(&[]), &[]).unwrap();
        assert!(g.v_attr.unwrap().iter().all(|&x| x == 0.0));
        assert_eq!(g.v_bary.unwrap(), vec![0.0; H * W * 2]);
    }

    #[test]
    fn pixels_outside_the_image_and_mismatched_output_gradients_are_refused() {
        let s = scene::<f64>(12);
        for bad in [(H * W) as i64, -1] {
            let err = forward(&s, Some(&[0, bad])).unwrap_err();
            assert!(
                matches!(
                    err,
                    Error::IndexOutOfRange {
                        arg: "pixels",
                        index: 1,
                        ..
                    }
                ),
                "{err}"
            );
        }
        let err = backward(&s, Some(&[0, 1]), &[0.0; C]).unwrap_err();
        assert!(matches!(err, Error::Shape { arg: "v_out", .. }), "{err}");
    }
}
