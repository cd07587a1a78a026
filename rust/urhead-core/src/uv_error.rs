//! The error-driven sampling's bookkeeping of one frame (paper Sec. 3.3): each pixel's
//! photometric error `‖I − I_gt‖₁ · mask` charged to a cell of a G × G UV grid, and added to
//! the float64 error and count grids in place. A covered pixel is charged at the UV it sees;
//! a pixel inside the mask (`mask > 0.5`) that the mesh misses (hair volume, a silhouette
//! the mesh has not reached) at the UV of the nearest covered pixel.
//!
//! "Nearest" is OpenCV's `distanceTransformWithLabels(DIST_L2, DIST_LABEL_PIXEL)`, which the
//! sampling used before this kernel, reproduced exactly, ties included: with labels OpenCV
//! always runs its two-pass 5×5 chamfer transform (weights 1, 1.4, 2.1969 in 16-bit fixed
//! point, whatever mask size is asked for), a candidate replaces the best so far only when
//! strictly smaller, in a fixed neighbour order. The chamfer metric is within ~2 % of the
//! Euclidean one; an exact Euclidean transform would move charges between equally good
//! pixels for no gain in the fit.
//!
//! The transform runs only on the bounding box of the covered pixels and the mask (which
//! holds every missed pixel). That changes no distance and no label: an optimal chamfer
//! path between two pixels never leaves their bounding box (two moves of opposite sign along an axis are always beaten
//! by a monotone combination, checked for every pair of the mask's moves), so a candidate
//! from outside the box is strictly worse than the best one inside and never wins or ties.
//!
//! The buffers (the box's distances and labels, the frame's per-cell sums) are kept per
//! thread across calls and reused: fresh, their megabytes cost more in page faults than
//! the whole kernel (measured ~750 faults, several ms, per training frame).
//!
//! The sums follow the order the torch code used (`bincount` over the covered pixels in
//! `pixels` order, then the missed ones in row-major order, the frame's sums added to the
//! grids at the end), so the grids are bitwise those of that code.

use std::cell::RefCell;

use crate::error::{check_indices, check_len, Error, Result};
use crate::memory::refill;
use crate::Real;

/// OpenCV's labelled `DIST_L2` chamfer weights (1, 1.4, 2.1969 as 65536, 91750, 143976),
/// halved: all three are even, so every comparison is unchanged and the range doubles.
const STRAIGHT: i32 = 32768;
const DIAGONAL: i32 = 45875;
const KNIGHT: i32 = 71988;
/// The distance of a pixel no seed reaches (yet): a candidate through it never wins, and
/// adding a weight to it does not overflow.
const FAR: i32 = i32::MAX - KNIGHT;
/// Width of the margin of `FAR` around the box (the 5×5 mask reaches two pixels).
const MARGIN: usize = 2;
/// The label of a pixel no seed reaches.
const NO_SEED: u32 = u32::MAX;
/// The largest `rows + cols` of the box: every reached pixel's distance, at most
/// `(rows + cols) · KNIGHT`, stays below `FAR`.
pub const MAX_EXTENT: usize = (FAR / KNIGHT) as usize;

/// A rectangle of pixels: rows `top..top + rows`, columns `left..left + cols`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Area {
    top: usize,
    left: usize,
    rows: usize,
    cols: usize,
}

impl Area {
    /// The bounding box of the pixels `(row, col)`, if any.
    fn around(pixels: impl Iterator<Item = (usize, usize)>) -> Option<Self> {
        let mut bounds: Option<[usize; 4]> = None;
        for (r, c) in pixels {
            let b = bounds.get_or_insert([r, r, c, c]);
            *b = [b[0].min(r), b[1].max(r), b[2].min(c), b[3].max(c)];
        }
        bounds.map(|[r0, r1, c0, c1]| Self {
            top: r0,
            left: c0,
            rows: r1 - r0 + 1,
            cols: c1 - c0 + 1,
        })
    }

    fn union(self, other: Self) -> Self {
        let top = self.top.min(other.top);
        let left = self.left.min(other.left);
        Self {
            top,
            left,
            rows: (self.top + self.rows).max(other.top + other.rows) - top,
            cols: (self.left + self.cols).max(other.left + other.cols) - left,
        }
    }
}

/// Flat pixel indices to `(row, col)`, dividing only when the row changes: the rasteriser
/// lists covered pixels row by row, so a frame costs a division per row, not per pixel.
struct RowCol {
    width: usize,
    row: usize,
    start: usize,
}

impl RowCol {
    fn new(width: usize) -> Self {
        Self {
            width,
            row: 0,
            start: 0,
        }
    }

    #[inline(always)]
    fn split(&mut self, p: usize) -> (usize, usize) {
        if p.wrapping_sub(self.start) >= self.width {
            self.row = p / self.width;
            self.start = self.row * self.width;
        }
        (self.row, p - self.start)
    }
}

/// Keeps the candidate `(dist, label)` when strictly nearer than `best` (OpenCV's rule: on a
/// tie the earlier candidate stays). Branch-free, so the row loops vectorise.
#[inline(always)]
fn relax(best: &mut (i32, u32), dist: i32, label: u32) {
    let nearer = dist < best.0;
    best.0 = if nearer { dist } else { best.0 };
    best.1 = if nearer { label } else { best.1 };
}

/// A neighbour of every pixel of a row: its distances and labels (slices aligned with the
/// row, see [`neighbour`]) and the weight of the step from it.
type Neighbour<'a> = (&'a [i32], &'a [u32], i32);

/// The pixels of padded row `(dist, label)` from column offset `offset` on (−2 ..= 2),
/// aligned with the box's columns, with the step weight `weight`.
fn neighbour<'a>(dist: &'a [i32], label: &'a [u32], offset: isize, weight: i32) -> Neighbour<'a> {
    let first = (MARGIN as isize + offset) as usize;
    (&dist[first..], &label[first..], weight)
}

/// Relaxes every pixel of a row (`dist`, `label`, the box's columns) with its neighbours in
/// finished rows, in the given order: independent per pixel, so it vectorises.
#[inline(always)]
fn relax_from_rows(dist: &mut [i32], label: &mut [u32], neighbours: [Neighbour<'_>; 7]) {
    let n = dist.len();
    let label = &mut label[..n];
    // Sliced to the row's length, so the loop needs no bounds checks.
    let neighbours = neighbours.map(|(d, l, w)| (&d[..n], &l[..n], w));
    for j in 0..n {
        let mut best = (dist[j], label[j]);
        for (d, l, w) in &neighbours {
            relax(&mut best, d[j] + w, l[j]);
        }
        (dist[j], label[j]) = best;
    }
}

/// OpenCV's `distanceTransformEx_5x5` on a box of the image: seeds are planted with
/// [`Chamfer::plant`], [`Chamfer::run`] labels every pixel of the box with its nearest
/// seed's label. Distances and labels live in `(rows + 4) × (cols + 4)` buffers with a
/// margin of `FAR` around the box.
#[derive(Default)]
struct Chamfer {
    top: usize,
    left: usize,
    rows: usize,
    cols: usize,
    stride: usize,
    dist: Vec<i32>,
    label: Vec<u32>,
}

impl Chamfer {
    /// Empties the buffers for `area`: no seed yet.
    fn reset(&mut self, area: Area) -> Result<()> {
        if area.rows + area.cols > MAX_EXTENT {
            return Err(Error::TooLarge {
                what: "nearest-covered-pixel search (rows + columns of the covered area)",
                requested: (area.rows + area.cols) as u128,
                limit: MAX_EXTENT as u128,
            });
        }
        (self.top, self.left, self.rows, self.cols) = (area.top, area.left, area.rows, area.cols);
        self.stride = area.cols + 2 * MARGIN;
        let len = (area.rows + 2 * MARGIN) * self.stride;
        refill(&mut self.dist, "nearest-pixel distances", len, FAR)?;
        refill(&mut self.label, "nearest-pixel labels", len, NO_SEED)
    }

    /// The buffer index of image pixel `(row, col)`, which must lie in the box.
    #[inline(always)]
    fn index(&self, row: usize, col: usize) -> usize {
        (row - self.top + MARGIN) * self.stride + col - self.left + MARGIN
    }

    /// Makes image pixel `(row, col)` a seed labelled `label`; false if it already was one.
    #[inline(always)]
    fn plant(&mut self, row: usize, col: usize, label: u32) -> bool {
        let i = self.index(row, col);
        let fresh = self.dist[i] != 0;
        (self.dist[i], self.label[i]) = (0, label);
        fresh
    }

    /// The box's row `i` (0-based): distances and labels, `cols` long.
    fn row(&self, i: usize) -> (&[i32], &[u32]) {
        let first = (i + MARGIN) * self.stride + MARGIN;
        (
            &self.dist[first..][..self.cols],
            &self.label[first..][..self.cols],
        )
    }

    /// Labels every pixel of the box with its nearest seed's label (`NO_SEED` when there is
    /// no seed). Each of OpenCV's two passes in two steps: the candidates from the rows
    /// already done (independent per pixel), then the one from the pixel before in the row
    /// (a sequential sweep), which OpenCV checks last. A seed keeps its label: no candidate
    /// beats distance 0.
    fn run(&mut self) {
        let (stride, columns) = (self.stride, MARGIN..MARGIN + self.cols);
        let (dist, label) = (&mut self.dist, &mut self.label);

        // Forward pass, top to bottom: neighbours above, then the one on the left.
        for r in MARGIN..MARGIN + self.rows {
            let (done, rest) = dist.split_at_mut(r * stride);
            let (done_label, rest_label) = label.split_at_mut(r * stride);
            let (row, row_label) = (&mut rest[..stride], &mut rest_label[..stride]);
            let up = |k: usize, offset: isize, weight: i32| {
                let line = (r - k) * stride..(r - k + 1) * stride;
                neighbour(&done[line.clone()], &done_label[line], offset, weight)
            };
            relax_from_rows(
                &mut row[columns.clone()],
                &mut row_label[columns.clone()],
                [
                    up(2, -1, KNIGHT),
                    up(2, 1, KNIGHT),
                    up(1, -2, KNIGHT),
                    up(1, -1, DIAGONAL),
                    up(1, 0, STRAIGHT),
                    up(1, 1, DIAGONAL),
                    up(1, 2, KNIGHT),
                ],
            );
            for c in columns.clone() {
                let mut best = (row[c], row_label[c]);
                relax(&mut best, row[c - 1] + STRAIGHT, row_label[c - 1]);
                (row[c], row_label[c]) = best;
            }
        }

        // Backward pass, bottom to top: neighbours below, then the one on the right. (OpenCV
        // skips pixels at distance ≤ 1 here; no candidate can beat those, so it is not needed.)
        for r in (MARGIN..MARGIN + self.rows).rev() {
            let (head, below) = dist.split_at_mut((r + 1) * stride);
            let (head_label, below_label) = label.split_at_mut((r + 1) * stride);
            let (row, row_label) = (&mut head[r * stride..], &mut head_label[r * stride..]);
            let down = |k: usize, offset: isize, weight: i32| {
                let line = (k - 1) * stride..k * stride;
                neighbour(&below[line.clone()], &below_label[line], offset, weight)
            };
            relax_from_rows(
                &mut row[columns.clone()],
                &mut row_label[columns.clone()],
                [
                    down(2, 1, KNIGHT),
                    down(2, -1, KNIGHT),
                    down(1, 2, KNIGHT),
                    down(1, 1, DIAGONAL),
                    down(1, 0, STRAIGHT),
                    down(1, -1, DIAGONAL),
                    down(1, -2, KNIGHT),
                ],
            );
            for c in columns.clone().rev() {
                let mut best = (row[c], row_label[c]);
                relax(&mut best, row[c + 1] + STRAIGHT, row_label[c + 1]);
                (row[c], row_label[c]) = best;
            }
        }
    }
}

/// `height · width` as a pixel count whose flat indices fit the labels (u32).
fn pixel_count(height: usize, width: usize) -> Result<usize> {
    let limit = NO_SEED as usize;
    match height.checked_mul(width) {
        Some(n) if n < limit => Ok(n),
        _ => Err(Error::TooLarge {
            what: "image pixels",
            requested: height as u128 * width as u128,
            limit: limit as u128,
        }),
    }
}

/// For every pixel of an `height × width` image (row-major), the flat index of the nearest
/// pixel where `covered` (H·W) is true, itself when covered, −1 when none is covered:
/// OpenCV's labelled `DIST_L2` transform, ties resolved as there (see the module docs).
pub fn nearest_covered(covered: &[bool], height: usize, width: usize) -> Result<Vec<i64>> {
    let n = pixel_count(height, width)?;
    check_len("covered", covered, n, &format!("(H, W) = ({height}, {width})"))?;
    if !covered.contains(&true) {
        return Ok(vec![-1; n]);
    }
    let mut chamfer = Chamfer::default();
    chamfer.reset(Area {
        top: 0,
        left: 0,
        rows: height,
        cols: width,
    })?;
    for (p, _) in covered.iter().enumerate().filter(|(_, &c)| c) {
        chamfer.plant(p / width, p % width, p as u32);
    }
    chamfer.run();
    let mut out = Vec::with_capacity(n);
    for i in 0..height {
        out.extend(chamfer.row(i).1.iter().map(|&l| l as i64));
    }
    Ok(out)
}

/// One frame's inputs to [`accumulate_uv_error`] (row-major, contiguous).
#[derive(Clone, Copy)]
pub struct UvErrorInputs<'a, T> {
    /// (H, W, 3) rendered image.
    pub image: &'a [T],
    /// (H, W, 3) ground truth.
    pub target: &'a [T],
    /// (H, W) mask in [0, 1]; a pixel is inside where `mask > 0.5`.
    pub mask: &'a [T],
    /// (P,) flat indices of the pixels the mesh covers, distinct.
    pub pixels: &'a [i64],
    /// (P, 2) the UV each covered pixel sees.
    pub uv: &'a [T],
    pub height: usize,
    pub width: usize,
}

impl<T: Real> UvErrorInputs<'_, T> {
    /// Checks every argument; returns H·W.
    fn validate(&self) -> Result<usize> {
        let (h, w) = (self.height, self.width);
        let n = pixel_count(h, w)?;
        check_len("image", self.image, n * 3, &format!("(H, W, 3) = ({h}, {w}, 3)"))?;
        check_len(
            "target",
            self.target,
            n * 3,
            &format!("(H, W, 3) = ({h}, {w}, 3)"),
        )?;
        check_len("mask", self.mask, n, &format!("(H, W) = ({h}, {w})"))?;
        let p = self.pixels.len();
        check_len("uv", self.uv, p * 2, &format!("(P, 2) with P = {p} like pixels"))?;
        check_indices("pixels", self.pixels, 0, n as i64)?;
        Ok(n)
    }

    /// Whether the mask holds pixel `p` (`mask > 0.5`; false for NaN).
    #[inline(always)]
    fn inside(&self, p: usize) -> bool {
        self.mask[p] > T::c(0.5)
    }

    /// `‖I − I_gt‖₁ · mask` at flat pixel `p`, summed as `((r + g) + b) · mask` in `T`.
    #[inline(always)]
    fn error(&self, p: usize) -> f64 {
        let (i, t) = (&self.image[3 * p..3 * p + 3], &self.target[3 * p..3 * p + 3]);
        let l1 = (i[0] - t[0]).abs() + (i[1] - t[1]).abs() + (i[2] - t[2]).abs();
        (l1 * self.mask[p]).to_f64().unwrap_or(f64::NAN)
    }

    /// The flat cell of a `side × side` grid holding covered pixel `k`'s UV: column
    /// `⌊u·G⌋`, row `⌊(1 − v)·G⌋` (the image of the atlas: v = 1 on top), each computed in
    /// `T` and clamped to the grid; NaN lands in row or column 0.
    #[inline(always)]
    fn cell(&self, k: usize, side: usize) -> usize {
        let g = T::c(side as f64);
        let clamp = |x: T| (x.to_f64().unwrap_or(0.0) as i64).clamp(0, side as i64 - 1) as usize;
        let (u, v) = (self.uv[2 * k], self.uv[2 * k + 1]);
        clamp((T::one() - v) * g) * side + clamp(u * g)
    }

    /// The bounding box of the mask's pixels (`mask > 0.5`), if any.
    fn mask_area(&self) -> Option<Area> {
        let rows = self.mask.chunks_exact(self.width).enumerate();
        Area::around(
            rows.filter_map(|(r, row)| {
                let first = row.iter().position(|&m| m > T::c(0.5))?;
                let last = row.iter().rposition(|&m| m > T::c(0.5))?;
                Some([(r, first), (r, last)])
            })
            .flatten(),
        )
    }
}

/// The buffers [`accumulate_uv_error`] reuses across calls on one thread.
#[derive(Default)]
struct Workspace {
    chamfer: Chamfer,
    /// (G·G, 2) the frame's error and count per cell, side by side (one cache line per
    /// charge); all zero between calls.
    sums: Vec<f64>,
}

thread_local! {
    static WORKSPACE: RefCell<Workspace> = RefCell::new(Workspace::default());
}

/// Adds one frame's UV error to `error` and `count` (both (G·G,) float64, G = `side`):
/// every covered pixel, and every pixel inside the mask the mesh misses (charged at the
/// nearest covered pixel's UV), adds its error to its cell and 1 to the cell's count.
/// Nothing is added when no pixel is covered. Non-finite image values are data: the cells
/// they are charged to become NaN or inf, as in the torch code.
pub fn accumulate_uv_error<T: Real>(
    inputs: &UvErrorInputs<'_, T>,
    side: usize,
    error: &mut [f64],
    count: &mut [f64],
) -> Result<()> {
    inputs.validate()?;
    let cells = side.checked_mul(side).filter(|&c| c > 0).ok_or(Error::Invalid {
        arg: "side",
        reason: format!("the grid side must be positive and its square fit usize, got {side}"),
    })?;
    check_len("error", error, cells, &format!("(G·G,) with G = {side}"))?;
    check_len("count", count, cells, &format!("(G·G,) with G = {side}"))?;
    let width = inputs.width;
    let mut rows_cols = RowCol::new(width);
    let Some(covered_area) = Area::around(inputs.pixels.iter().map(|&p| rows_cols.split(p as usize))) else {
        return Ok(());
    };
    // Every missed pixel lies in the mask's box: the union holds seeds and queries.
    let area = inputs.mask_area().map_or(covered_area, |m| m.union(covered_area));
    WORKSPACE.with_borrow_mut(|Workspace { chamfer, sums }| {
        chamfer.reset(area)?;
        for (k, &p) in inputs.pixels.iter().enumerate() {
            let (row, col) = rows_cols.split(p as usize);
            if !chamfer.plant(row, col, k as u32) {
                return Err(Error::Invalid {
                    arg: "pixels",
                    reason: format!("pixel {p} is listed more than once"),
                });
            }
        }
        if sums.len() != 2 * cells {
            refill(sums, "UV error and count of one frame", 2 * cells, 0.0)?;
        }
        let mut charge = |k: usize, p: usize| {
            let cell = inputs.cell(k, side);
            sums[2 * cell] += inputs.error(p);
            sums[2 * cell + 1] += 1.0;
        };
        for (k, &p) in inputs.pixels.iter().enumerate() {
            charge(k, p as usize);
        }
        // Before the search, only seeds are at distance 0.
        let box_pixel = |i: usize, j: usize| (area.top + i) * width + area.left + j;
        let missed =
            |i: usize, dist: &[i32]| (0..area.cols).any(|j| dist[j] != 0 && inputs.inside(box_pixel(i, j)));
        if (0..area.rows).any(|i| missed(i, chamfer.row(i).0)) {
            chamfer.run();
            for i in 0..area.rows {
                let (dist, label) = chamfer.row(i);
                for j in 0..area.cols {
                    let p = box_pixel(i, j);
                    if dist[j] != 0 && inputs.inside(p) {
                        charge(label[j] as usize, p);
                    }
                }
            }
        }
        for ((e, c), s) in error
            .iter_mut()
            .zip(count.iter_mut())
            .zip(sums.chunks_exact_mut(2))
        {
            *e += s[0];
            *c += s[1];
            s.fill(0.0);
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use std::collections::BinaryHeap;

    use super::*;
    use crate::testing::Rng;

    /// Chamfer distance (in the kernel's units) from `(0, 0)` to every offset of a
    /// `(2h − 1) × (2w − 1)` window, by Dijkstra over the mask's 16 moves: the metric the
    /// two passes must reach.
    fn chamfer_metric(h: usize, w: usize) -> impl Fn(usize, usize, usize, usize) -> i64 {
        let moves: Vec<(i64, i64, i64)> = (-2i64..=2)
            .flat_map(|r| (-2i64..=2).map(move |c| (r, c)))
            .filter_map(|(r, c)| match (r.abs().min(c.abs()), r.abs().max(c.abs())) {
                (0, 1) => Some((r, c, STRAIGHT as i64)),
                (1, 1) => Some((r, c, DIAGONAL as i64)),
                (1, 2) => Some((r, c, KNIGHT as i64)),
                _ => None,
            })
            .collect();
        let (rows, cols) = (2 * h as i64 - 1, 2 * w as i64 - 1);
        let mut best = vec![i64::MAX; (rows * cols) as usize];
        let centre = ((h as i64 - 1) * cols + w as i64 - 1) as usize;
        best[centre] = 0;
        let mut queue = BinaryHeap::from([(0i64, centre)]);
        while let Some((neg, at)) = queue.pop() {
            if -neg > best[at] {
                continue;
            }
            let (r, c) = (at as i64 / cols, at as i64 % cols);
            for &(dr, dc, weight) in &moves {
                let (nr, nc) = (r + dr, c + dc);
                if (0..rows).contains(&nr) && (0..cols).contains(&nc) {
                    let next = (nr * cols + nc) as usize;
                    if best[at] + weight < best[next] {
                        best[next] = best[at] + weight;
                        queue.push((-best[next], next));
                    }
                }
            }
        }
        move |r0, c0, r1, c1| {
            let dr = r1 as i64 - r0 as i64 + h as i64 - 1;
            let dc = c1 as i64 - c0 as i64 + w as i64 - 1;
            best[(dr * cols + dc) as usize]
        }
    }

    #[test]
    fn labels_a_seed_at_the_least_chamfer_distance() {
        let mut rng = Rng::new(1);
        for trial in 0..40 {
            let (h, w) = (1 + trial % 9 + trial / 4, 1 + (trial * 7) % 23);
            let density = [0.01, 0.05, 0.2, 0.6][trial % 4];
            let covered: Vec<bool> = (0..h * w).map(|_| rng.uniform(0.0, 1.0) < density).collect();
            let nearest = nearest_covered(&covered, h, w).unwrap();
            let seeds: Vec<usize> = (0..h * w).filter(|&p| covered[p]).collect();
            if seeds.is_empty() {
                assert!(nearest.iter().all(|&l| l == -1));
                continue;
            }
            let metric = chamfer_metric(h, w);
            let d = |p: usize, s: usize| metric(p / w, p % w, s / w, s % w);
            for p in 0..h * w {
                let label = nearest[p] as usize;
                assert!(covered[label], "trial {trial}: pixel {p} labelled off the seeds");
                let least = seeds.iter().map(|&s| d(p, s)).min().unwrap();
                assert_eq!(d(p, label), least, "trial {trial}: pixel {p}");
            }
        }
    }

    #[test]
    fn ties_go_where_opencv_sends_them() {
        // Expected labels from cv2.distanceTransformWithLabels(DIST_L2, 3, DIST_LABEL_PIXEL).
        let case = |h: usize, w: usize, seeds: &[usize]| {
            let covered: Vec<bool> = (0..h * w).map(|p| seeds.contains(&p)).collect();
            nearest_covered(&covered, h, w).unwrap()
        };
        assert_eq!(case(1, 3, &[0, 2]), [0, 0, 2]);
        let corners = [
            [0, 0, 0, 5, 5, 5],
            [0, 0, 0, 5, 5, 5],
            [0, 0, 0, 5, 5, 5],
            [0, 0, 29, 29, 29, 29],
            [0, 29, 29, 29, 29, 29],
        ];
        assert_eq!(case(5, 6, &[0, 5, 29]), corners.concat());
        let diamond = [
            [10, 2, 2, 2, 2],
            [10, 2, 2, 2, 14],
            [10, 10, 2, 14, 14],
            [10, 10, 22, 14, 14],
            [10, 22, 22, 22, 14],
        ];
        assert_eq!(case(5, 5, &[2, 10, 14, 22]), diamond.concat());
    }

    /// A frame: `h × w` f32 images, a mask that is a disc larger than the covered disc
    /// (pixels the mesh misses around it), smooth UVs; `pad` empty pixels on every side.
    struct Frame {
        image: Vec<f32>,
        target: Vec<f32>,
        mask: Vec<f32>,
        pixels: Vec<i64>,
        uv: Vec<f32>,
        h: usize,
        w: usize,
    }

    impl Frame {
        fn new(h: usize, w: usize, pad: usize, seed: u64) -> Self {
            let mut rng = Rng::new(seed);
            let (ph, pw) = (h + 2 * pad, w + 2 * pad);
            let mut f = Frame {
                image: vec![0.0; ph * pw * 3],
                target: vec![0.0; ph * pw * 3],
                mask: vec![0.0; ph * pw],
                pixels: vec![],
                uv: vec![],
                h: ph,
                w: pw,
            };
            for r in 0..h {
                for c in 0..w {
                    let p = (r + pad) * pw + c + pad;
                    for k in 0..3 {
                        f.image[3 * p + k] = rng.uniform(0.0, 1.0) as f32;
                        f.target[3 * p + k] = rng.uniform(0.0, 1.0) as f32;
                    }
                    let radius = (r as f64 - h as f64 / 2.0).hypot(c as f64 - w as f64 / 3.0);
                    f.mask[p] = if radius < 0.45 * h as f64 {
                        rng.uniform(0.5, 1.0) as f32
                    } else {
                        0.0
                    };
                    if radius < 0.3 * h as f64 || rng.uniform(0.0, 1.0) < 0.02 {
                        f.pixels.push(p as i64);
                        f.uv.extend([c as f32 / w as f32, 1.0 - r as f32 / h as f32]);
                    }
                }
            }
            f
        }

        fn inputs(&self) -> UvErrorInputs<'_, f32> {
            UvErrorInputs {
                image: &self.image,
                target: &self.target,
                mask: &self.mask,
                pixels: &self.pixels,
                uv: &self.uv,
                height: self.h,
                width: self.w,
            }
        }

        /// The grids after adding this frame to grids holding `start`.
        fn grids(&self, side: usize, start: f64) -> (Vec<f64>, Vec<f64>) {
            let (mut error, mut count) = (vec![start; side * side], vec![start; side * side]);
            accumulate_uv_error(&self.inputs(), side, &mut error, &mut count).unwrap();
            (error, count)
        }
    }

    #[test]
    fn charges_covered_pixels_then_missed_ones_at_the_nearest_covered_uv() {
        let f = Frame::new(20, 30, 0, 2);
        let side = 8;
        // The same sums, written plainly: per-frame sums in the documented order.
        let mut sums = vec![0.0f64; 2 * side * side];
        let inputs = f.inputs();
        let mut add = |k: usize, p: usize| {
            let cell = inputs.cell(k, side);
            sums[2 * cell] += inputs.error(p);
            sums[2 * cell + 1] += 1.0;
        };
        for (k, &p) in f.pixels.iter().enumerate() {
            add(k, p as usize);
        }
        let covered: Vec<bool> = (0..f.h * f.w).map(|p| f.pixels.contains(&(p as i64))).collect();
        let nearest = nearest_covered(&covered, f.h, f.w).unwrap();
        let mut missed = 0;
        for p in 0..f.h * f.w {
            if !covered[p] && f.mask[p] > 0.5 {
                let k = f.pixels.iter().position(|&q| q == nearest[p]).unwrap();
                add(k, p);
                missed += 1;
            }
        }
        assert!(missed > 20, "the frame has pixels the mesh misses");
        let (error, count) = f.grids(side, 0.25);
        for cell in 0..side * side {
            assert_eq!(error[cell], 0.25 + sums[2 * cell]);
            assert_eq!(count[cell], 0.25 + sums[2 * cell + 1]);
        }
        assert_eq!(
            count.iter().sum::<f64>(),
            0.25 * 64.0 + (f.pixels.len() + missed) as f64
        );
    }

    #[test]
    fn the_searched_box_changes_nothing() {
        // The same frame inside a larger empty image: the box search equals the whole one.
        for seed in 0..4 {
            let tight = Frame::new(17, 23, 0, seed).grids(16, 0.0);
            let padded = Frame::new(17, 23, 9, seed).grids(16, 0.0);
            assert_eq!(tight, padded);
        }
    }

    #[test]
    fn reused_buffers_leave_no_trace() {
        let small = Frame::new(9, 11, 1, 3);
        let large = Frame::new(40, 37, 0, 4);
        let first = (large.grids(8, 0.0), small.grids(4, 0.0));
        // Other sizes and grids in between, an error half-way: the same results after.
        assert_eq!(small.grids(16, 0.0), Frame::new(9, 11, 1, 3).grids(16, 0.0));
        let mut bad = small.pixels.clone();
        bad.push(bad[0]);
        let inputs = UvErrorInputs {
            pixels: &bad,
            uv: &[small.uv.clone(), vec![0.5; 2]].concat(),
            ..small.inputs()
        };
        assert!(accumulate_uv_error(&inputs, 4, &mut [0.0; 16], &mut [0.0; 16]).is_err());
        assert_eq!((large.grids(8, 0.0), small.grids(4, 0.0)), first);
    }

    #[test]
    fn no_covered_pixel_no_missed_pixel_and_nan() {
        let mut f = Frame::new(12, 12, 2, 5);
        let side = 4;
        // Nothing covered: nothing added.
        let none = UvErrorInputs {
            pixels: &[],
            uv: &[],
            ..f.inputs()
        };
        let (mut error, mut count) = (vec![1.0; 16], vec![1.0; 16]);
        accumulate_uv_error(&none, side, &mut error, &mut count).unwrap();
        assert_eq!((error, count), (vec![1.0; 16], vec![1.0; 16]));
        // An empty mask: covered pixels add zero error, each counts once.
        let mask = std::mem::replace(&mut f.mask, vec![0.0; f.h * f.w]);
        let (error, count) = f.grids(side, 0.0);
        assert!(error.iter().all(|&e| e == 0.0));
        assert_eq!(count.iter().sum::<f64>(), f.pixels.len() as f64);
        f.mask = mask;
        // NaN in the image: the cell it is charged to, and no other, becomes NaN.
        let p = f.pixels[5] as usize;
        f.image[3 * p + 1] = f32::NAN;
        let (error, _) = f.grids(side, 0.0);
        let nan_cell = f.inputs().cell(5, side);
        for (cell, e) in error.iter().enumerate() {
            assert_eq!(e.is_nan(), cell == nan_cell, "cell {cell}");
        }
    }

    #[test]
    fn rejects_bad_arguments_before_touching_the_grids() {
        let f = Frame::new(6, 7, 0, 6);
        let ok = f.inputs();
        let run = |inputs: &UvErrorInputs<'_, f32>, side: usize, cells: usize| {
            let (mut error, mut count) = (vec![0.5; cells], vec![0.5; cells]);
            let result = accumulate_uv_error(inputs, side, &mut error, &mut count);
            let untouched = error.iter().chain(&count).all(|&x| x == 0.5);
            assert!(result.is_ok() || untouched, "grids touched by a call that failed");
            result.err()
        };
        assert!(run(&ok, 4, 16).is_none());
        let shape = |arg: &str, e: Option<Error>| matches!(e, Some(Error::Shape { arg: a, .. }) if a == arg);
        assert!(shape(
            "image",
            run(
                &UvErrorInputs {
                    image: &f.image[3..],
                    ..ok
                },
                4,
                16
            )
        ));
        assert!(shape(
            "mask",
            run(
                &UvErrorInputs {
                    mask: &f.mask[1..],
                    ..ok
                },
                4,
                16
            )
        ));
        assert!(shape("uv", run(&UvErrorInputs { uv: &f.uv[2..], ..ok }, 4, 16)));
        assert!(shape("error", run(&ok, 4, 15)));
        let out_of_range = [f.pixels.clone(), vec![42]].concat();
        let uv = [f.uv.clone(), vec![0.5; 2]].concat();
        let e = run(
            &UvErrorInputs {
                pixels: &out_of_range,
                uv: &uv,
                ..ok
            },
            4,
            16,
        );
        assert!(matches!(
            e,
            Some(Error::IndexOutOfRange {
                arg: "pixels",
                value: 42,
                ..
            })
        ));
        let twice = [f.pixels.clone(), vec![f.pixels[3]]].concat();
        let e = run(
            &UvErrorInputs {
                pixels: &twice,
                uv: &uv,
                ..ok
            },
            4,
            16,
        );
        assert!(matches!(e, Some(Error::Invalid { arg: "pixels", .. })));
        assert!(matches!(run(&ok, 0, 0), Some(Error::Invalid { arg: "side", .. })));
        let e = nearest_covered(&[true; 5], 2, 3).unwrap_err();
        assert!(matches!(e, Error::Shape { arg: "covered", .. }));
    }
}
