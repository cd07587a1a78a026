//! Tile binning: every visible Gaussian is listed in each 16×16 tile its bounding box
//! touches — except, with a mesh depth map, the tiles where it lies behind the mesh at
//! every pixel (deeper than the tile's largest `depth_map + depth_eps`: every sample there
//! would fail the occlusion test, so the lists, the images and the gradients are those of
//! listing it) — each tile's list in (depth, index) order — the order a stable sort of
//! (tile, depth) keys with index tie-breaks gives. Built by one global depth sort
//! followed by a counting sort by tile, which also yields the inverse index (each
//! Gaussian's intersections in row-major tile order) that the backward reduces over.

use rayon::prelude::*;

use super::{RasterInputs, MAX_INTERSECTIONS, TILE};
use crate::error::{Error, Result};
use crate::memory::{zeroed, DisjointWrites};
use crate::Real;

/// Gaussians of the depth order per parallel task of the counting sort's scatter.
const FILL_CHUNK: usize = 2048;

/// Tile lists and their inverse. Built by [`Binning::new`], reused by the backward.
#[derive(Debug, Clone)]
pub struct Binning {
    pub tiles_x: usize,
    pub tiles_y: usize,
    /// `(tiles + 1)`: tile t lists `tile_gaussians[tile_offsets[t]..tile_offsets[t+1]]`.
    pub tile_offsets: Vec<u32>,
    /// `(I,)` Gaussian ids, front to back within each tile.
    pub tile_gaussians: Vec<u32>,
    /// `(N + 1)`: Gaussian g's intersections are
    /// `isect_of_gaussian[gaussian_offsets[g]..gaussian_offsets[g+1]]`.
    pub gaussian_offsets: Vec<u32>,
    /// `(I,)` positions in `tile_gaussians`, row-major tile order per Gaussian.
    pub isect_of_gaussian: Vec<u32>,
    /// Image size the binning was made for.
    pub width: usize,
    pub height: usize,
}

/// Half-open tile rectangle `[x0, x1) × [y0, y1)` a Gaussian touches; empty if culled.
#[inline]
pub(super) fn tile_rect<T: Real>(
    inputs: &RasterInputs<T>,
    g: usize,
    tiles_x: usize,
    tiles_y: usize,
) -> [usize; 4] {
    let (rx, ry) = (inputs.radii[g * 2], inputs.radii[g * 2 + 1]);
    if rx <= 0 || ry <= 0 || !(inputs.opacities[g] >= T::c(super::ALPHA_MIN)) {
        return [0; 4];
    }
    let mx = inputs.means2d[g * 2].to_f64().unwrap_or(f64::NAN);
    let my = inputs.means2d[g * 2 + 1].to_f64().unwrap_or(f64::NAN);
    let t = TILE as f64;
    let span = |lo: f64, hi: f64, n: usize| -> (usize, usize) {
        let a = (lo / t).floor().clamp(0.0, n as f64);
        let b = (hi / t).ceil().clamp(0.0, n as f64);
        (a as usize, b as usize)
    };
    let (x0, x1) = span(mx - rx as f64, mx + rx as f64, tiles_x);
    let (y0, y1) = span(my - ry as f64, my + ry as f64, tiles_y);
    if x0 >= x1 || y0 >= y1 {
        return [0; 4];
    }
    [x0, x1, y0, y1]
}

impl Binning {
    pub fn new<T: Real>(inputs: &RasterInputs<T>) -> Result<Self> {
        let n = inputs.num_gaussians;
        let tiles_x = inputs.width.div_ceil(TILE);
        let tiles_y = inputs.height.div_ceil(TILE);
        let num_tiles = tiles_x * tiles_y;
        let rects: Vec<[usize; 4]> = (0..n)
            .into_par_iter()
            .map(|g| tile_rect(inputs, g, tiles_x, tiles_y))
            .collect();
        let count = |r: &[usize; 4]| (r[1] - r[0]) * (r[3] - r[2]);
        let total: u128 = rects.iter().map(|r| count(r) as u128).sum();
        if total > MAX_INTERSECTIONS as u128 {
            return Err(Error::TooLarge {
                what: "tile intersections (Gaussians × tiles covered; shrink huge Gaussians)",
                requested: total,
                limit: MAX_INTERSECTIONS as u128,
            });
        }
        // Behind the mesh in a whole tile: hidden there (see the module docs).
        let deepest = inputs
            .depth_map
            .map(|depth| deepest_limits(inputs, depth, tiles_x, tiles_y));
        let listed = |g: usize, tile: usize| deepest.as_ref().is_none_or(|d| inputs.depths[g] <= d[tile]);
        // One pass over every Gaussian's listed tiles, in chunks: its own count, and each
        // tile's (integer counts per chunk, summed: independent of the chunking). The
        // front-to-back order (a serial sort) is made at the same time.
        const CHUNK: usize = 4096;
        let count_chunks = || -> Vec<(Vec<u32>, Vec<u32>)> {
            (0..n.div_ceil(CHUNK))
                .into_par_iter()
                .map(|chunk| {
                    let mut tiles = vec![0u32; num_tiles];
                    let per_gaussian = (chunk * CHUNK..((chunk + 1) * CHUNK).min(n))
                        .map(|g| {
                            let mut count = 0u32;
                            for_each_tile(rects[g], tiles_x, |tile| {
                                if listed(g, tile) {
                                    tiles[tile] += 1;
                                    count += 1;
                                }
                            });
                            count
                        })
                        .collect();
                    (per_gaussian, tiles)
                })
                .collect()
        };
        let (order, chunks) = rayon::join(|| depth_order(inputs, &rects), count_chunks);
        let mut gaussian_offsets = Vec::with_capacity(n + 1);
        gaussian_offsets.push(0u32);
        let mut tile_counts = vec![0u32; num_tiles];
        for (per_gaussian, tiles) in &chunks {
            for &k in per_gaussian {
                gaussian_offsets.push(gaussian_offsets.last().unwrap() + k);
            }
            for (sum, k) in tile_counts.iter_mut().zip(tiles) {
                *sum += k;
            }
        }
        let total = *gaussian_offsets.last().unwrap() as usize;
        let mut tile_offsets = Vec::with_capacity(num_tiles + 1);
        tile_offsets.push(0u32);
        for c in &tile_counts {
            tile_offsets.push(tile_offsets.last().unwrap() + c);
        }
        // The counting sort's scatter in parallel chunks of the depth order: a chunk's
        // intersections in a tile go after the earlier chunks' (counted first), so every
        // position is the one a serial pass in depth order gives.
        let order_chunks: Vec<&[u32]> = order.chunks(FILL_CHUNK).collect();
        let chunk_counts: Vec<Vec<u32>> = order_chunks
            .par_iter()
            .map(|chunk| {
                let mut counts = vec![0u32; num_tiles];
                for &g in *chunk {
                    for_each_tile(rects[g as usize], tiles_x, |tile| {
                        counts[tile] += u32::from(listed(g as usize, tile));
                    });
                }
                counts
            })
            .collect();
        let mut cursor: Vec<u32> = tile_offsets[..num_tiles].to_vec();
        let mut cursors = Vec::with_capacity(chunk_counts.len());
        for counts in &chunk_counts {
            cursors.push(cursor.clone());
            for (c, k) in cursor.iter_mut().zip(counts) {
                *c += k;
            }
        }
        let mut tile_gaussians: Vec<u32> = zeroed("tile intersections", total)?;
        let mut isect_of_gaussian: Vec<u32> = zeroed("intersection order", total)?;
        let (tile_out, isect_out) = (
            DisjointWrites::new(&mut tile_gaussians),
            DisjointWrites::new(&mut isect_of_gaussian),
        );
        order_chunks
            .into_par_iter()
            .zip(cursors)
            .for_each(|(chunk, mut cursor)| {
                for &g in chunk {
                    let mut slot = gaussian_offsets[g as usize] as usize;
                    for_each_tile(rects[g as usize], tiles_x, |tile| {
                        if listed(g as usize, tile) {
                            let pos = cursor[tile];
                            cursor[tile] += 1;
                            // SAFETY: `pos` is in this chunk's own range of the tile's
                            // list (the chunks' cursors start where the earlier chunks'
                            // counts end), and `slot` in this Gaussian's own range of
                            // `isect_of_gaussian` (each Gaussian is in one chunk).
                            unsafe {
                                tile_out.write(pos as usize, g);
                                isect_out.write(slot, pos);
                            }
                            slot += 1;
                        }
                    });
                }
            });
        Ok(Self {
            tiles_x,
            tiles_y,
            tile_offsets,
            tile_gaussians,
            gaussian_offsets,
            isect_of_gaussian,
            width: inputs.width,
            height: inputs.height,
        })
    }

    pub fn num_intersections(&self) -> usize {
        self.tile_gaussians.len()
    }
}

/// Calls `visit` with each tile of `rect` (`[x0, x1, y0, y1]`, in tiles), row by row.
/// Plain nested loops: as a `flat_map` iterator the walk's fold was left out of line in
/// some builds, which cost a 512² splatting forward ~1 ms (measured on the step's inputs).
#[inline(always)]
fn for_each_tile(rect: [usize; 4], tiles_x: usize, mut visit: impl FnMut(usize)) {
    let [x0, x1, y0, y1] = rect;
    for ty in y0..y1 {
        for tx in x0..x1 {
            visit(ty * tiles_x + tx);
        }
    }
}

/// `(tiles_y, tiles_x)` each tile's largest `depth_map + depth_eps` (the limit the
/// occlusion test compares a sample's depth with; a NaN limit, which no depth passes, is
/// left out of the maximum).
fn deepest_limits<T: Real>(inputs: &RasterInputs<T>, depth: &[T], tiles_x: usize, tiles_y: usize) -> Vec<T> {
    let (w, h) = (inputs.width, inputs.height);
    (0..tiles_y)
        .into_par_iter()
        .flat_map_iter(|ty| {
            // Per tile, one running maximum per pixel column (an element-wise max that
            // vectorises), reduced over the columns at the end.
            let mut columns = vec![T::neg_infinity(); tiles_x * TILE];
            for y in ty * TILE..((ty + 1) * TILE).min(h) {
                for (deepest, &d) in columns.iter_mut().zip(&depth[y * w..(y + 1) * w]) {
                    *deepest = deepest.max(d + inputs.depth_eps);
                }
            }
            columns
                .chunks_exact(TILE)
                .map(|tile| tile.iter().fold(T::neg_infinity(), |a, &b| a.max(b)))
                .collect::<Vec<_>>()
        })
        .collect()
}

/// Front-to-back order of the visible Gaussians; the index breaks depth ties. When every
/// depth is exactly a float32 (always for float32 inputs) the (depth, index) key packs
/// into one u64, which sorts faster than a tuple.
fn depth_order<T: Real>(inputs: &RasterInputs<T>, rects: &[[usize; 4]]) -> Vec<u32> {
    let visible = |g: &usize| rects[*g][1] > rects[*g][0] && rects[*g][3] > rects[*g][2];
    let n = inputs.num_gaussians;
    let as_f32 = |d: T| d.to_f32().filter(|&f| T::c(f as f64) == d);
    if (0..n).filter(visible).all(|g| as_f32(inputs.depths[g]).is_some()) {
        let keys: Vec<u64> = (0..n)
            .filter(visible)
            .map(|g| {
                let bits = as_f32(inputs.depths[g]).unwrap_or(0.0).to_bits();
                let ordered = if bits >> 31 == 1 { !bits } else { bits | 1 << 31 };
                (ordered as u64) << 32 | g as u64
            })
            .collect();
        sort_by_high_word(keys).into_iter().map(|k| k as u32).collect()
    } else {
        let mut keys: Vec<(u64, u32)> = (0..n)
            .filter(visible)
            .map(|g| (depth_key(inputs.depths[g]), g as u32))
            .collect();
        keys.par_sort_unstable();
        keys.into_iter().map(|(_, g)| g).collect()
    }
}

/// `keys` sorted by their high 32 bits, stably: an LSD radix sort, 8 bits a pass, skipping
/// the passes where every key has the same byte (a head's depths share their exponent).
/// Keys made in ascending order of their low word come out ordered by (high, low) — the
/// order a sort of the whole keys gives — in a few linear passes instead of a comparison
/// sort (~4× faster at 24k keys).
fn sort_by_high_word(mut keys: Vec<u64>) -> Vec<u64> {
    let mut spare = vec![0u64; keys.len()];
    for shift in [32, 40, 48, 56] {
        let digit = |k: u64| (k >> shift) as usize & 0xFF;
        let mut counts = [0usize; 256];
        for &k in &keys {
            counts[digit(k)] += 1;
        }
        if counts.contains(&keys.len()) {
            continue;
        }
        let mut next = [0usize; 256];
        let mut sum = 0;
        for (start, count) in next.iter_mut().zip(counts) {
            *start = sum;
            sum += count;
        }
        for &k in &keys {
            let slot = &mut next[digit(k)];
            spare[*slot] = k;
            *slot += 1;
        }
        std::mem::swap(&mut keys, &mut spare);
    }
    keys
}

/// A sort key ordering depths ascending (total order on the f64 bit pattern).
#[inline]
fn depth_key<T: Real>(d: T) -> u64 {
    let bits = d.to_f64().unwrap_or(f64::NAN).to_bits();
    // Flip negatives entirely and set the sign bit of positives: ascending as unsigned.
    if bits >> 63 == 1 {
        !bits
    } else {
        bits | 1 << 63
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;

    /// The tile lists and their inverse, built in parallel chunks of the depth order, are
    /// the serial definition's: each tile's listed Gaussians by (depth, index), and each
    /// Gaussian's intersections in row-major tile order — on any thread count, for a scene
    /// of several chunks with a depth map that hides some tiles.
    #[test]
    fn lists_are_the_definitions_on_any_thread_count() {
        use crate::splat::{project_forward, synthetic::SyntheticSplat};
        use crate::testing::on_threads;
        let s = SyntheticSplat::<f32>::head(3 * FILL_CHUNK + 77, 96, 0.75, 4);
        let proj = project_forward(&s.camera, &s.inputs(Some(0))).unwrap();
        let px = 96 * 96;
        let depth: Vec<f32> = (0..px).map(|i| if i % 96 < 40 { 0.74 } else { 10.0 }).collect();
        let inputs = s.raster_inputs(&proj, None, Some(&depth), 0.01);
        let (tiles_x, tiles_y) = (96usize.div_ceil(TILE), 96usize.div_ceil(TILE));
        let deepest = deepest_limits(&inputs, &depth, tiles_x, tiles_y);
        let mut expected: Vec<Vec<u32>> = vec![Vec::new(); tiles_x * tiles_y];
        for g in 0..inputs.num_gaussians {
            for_each_tile(tile_rect(&inputs, g, tiles_x, tiles_y), tiles_x, |tile| {
                if inputs.depths[g] <= deepest[tile] {
                    expected[tile].push(g as u32);
                }
            });
        }
        for list in &mut expected {
            list.sort_by(|&a, &b| {
                inputs.depths[a as usize]
                    .total_cmp(&inputs.depths[b as usize])
                    .then(a.cmp(&b))
            });
        }
        assert!(expected.iter().map(Vec::len).sum::<usize>() > 2 * FILL_CHUNK);
        for threads in [1, 3] {
            let b = on_threads(threads, || Binning::new(&inputs).unwrap());
            for (tile, list) in expected.iter().enumerate() {
                let got = &b.tile_gaussians[b.tile_offsets[tile] as usize..b.tile_offsets[tile + 1] as usize];
                assert_eq!(got, &list[..], "tile {tile}, {threads} threads");
            }
            for g in 0..inputs.num_gaussians {
                let own =
                    &b.isect_of_gaussian[b.gaussian_offsets[g] as usize..b.gaussian_offsets[g + 1] as usize];
                let tiles: Vec<usize> = own
                    .iter()
                    .map(|&pos| b.tile_offsets.partition_point(|&o| o <= pos) - 1)
                    .collect();
                assert!(own.iter().all(|&pos| b.tile_gaussians[pos as usize] == g as u32));
                assert!(
                    tiles.windows(2).all(|w| w[0] < w[1]),
                    "Gaussian {g}: row-major tiles"
                );
            }
        }
    }

    #[test]
    fn radix_order_is_the_sorted_order() {
        let mut rng = Rng::new(3);
        for (n, spread) in [(0usize, 1.0f32), (1, 1.0), (5000, 1e-3), (5000, 1e30), (300, 0.0)] {
            let keys: Vec<u64> = (0..n)
                .map(|g| {
                    let d = 0.7 + spread * rng.vec::<f32>(1, -1.0, 1.0)[0];
                    let d = if g % 97 == 0 { -d } else { d };
                    let bits = d.to_bits();
                    let ordered = if bits >> 31 == 1 { !bits } else { bits | 1 << 31 };
                    (ordered as u64) << 32 | g as u64
                })
                .collect();
            let mut expected = keys.clone();
            expected.sort_unstable();
            assert_eq!(sort_by_high_word(keys), expected, "n = {n}, spread {spread}");
        }
    }
}
