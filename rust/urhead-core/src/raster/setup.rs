//! Triangle setup shared by the rasterizers' forward and backward passes: clipping against
//! the near plane and a guard band, fixed-point edge functions for watertight coverage, and
//! the barycentric planes every per-pixel quantity is computed from.
//!
//! Geometry arrives as homogeneous screen positions `h = (X, Y, W)`: the pixel position is
//! `(X/W, Y/W)` and `W` is the linear depth (`h = K·p_cam` for a camera, `W = 1` for the UV
//! layout). The perspective-correct barycentric weight of vertex `i` at a pixel centre `e`
//! (homogeneous, `(x, y, 1)`) is `λ̃_i = e·(h_j × h_k)`, normalised to sum to one; this holds
//! for vertices behind the camera too, so clipping only decides coverage and barycentrics
//! always refer to the original triangle. The setup runs in f64 whatever the kernel's
//! float type; per-pixel work runs in `T`.

use rayon::prelude::*;

use super::TILE_ROWS;
use crate::mat3::map3;
use crate::Real;

/// Sub-pixel bits of the snapped screen positions used for coverage.
pub const SUBPIXEL_BITS: u32 = 8;
const SUBPIXEL_SCALE: f64 = (1u32 << SUBPIXEL_BITS) as f64;
const HALF_PIXEL: i64 = 1 << (SUBPIXEL_BITS - 1);
/// Geometry further than this many pixels outside the viewport is clipped away. It never
/// changes which pixels are covered; it only keeps the fixed-point edge functions small
/// (|coordinate| < 2^23 sub-pixel units, products < 2^49).
pub const GUARD_BAND_PX: f64 = 16384.0;
/// Capacity of a clipped polygon: a triangle clipped by 5 planes has at most 8 vertices
/// in exact arithmetic; rounding can add crossings, each plane at most ×1.5.
const MAX_POLY: usize = 32;
/// Triangles per parallel setup chunk.
const SETUP_CHUNK: usize = 512;

/// Homogeneous screen position `(X, Y, W)`.
pub(crate) type Hom = [f64; 3];

/// The render target and clip distances.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Viewport {
    pub width: usize,
    pub height: usize,
    /// Clip plane `W = near`; 0 for the UV layout (where `W = 1`).
    pub near: f64,
}

impl Viewport {
    pub fn num_tiles(&self) -> usize {
        self.height.div_ceil(TILE_ROWS)
    }
}

/// One triangle's barycentric planes, relative to an integer pixel `origin` so the plane
/// coefficients stay small and the per-pixel sums do not cancel.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TrianglePlanes<T> {
    /// `λ̃_i = coef[i][0]·ex + coef[i][1]·ey + coef[i][2]` with `(ex, ey)` the pixel centre
    /// minus `origin`; `coef[i] = scale · (h'_j × h'_k)` (see [`PlaneFrame`]).
    pub coef: [[T; 3]; 3],
    /// Linear depth `W` of each vertex.
    pub depth: [T; 3],
    pub origin: [i32; 2],
}

/// The f64 quantities the planes are made from, recomputed bit-identically by the
/// backward pass from the vertices and the origin.
#[derive(Debug, Clone, Copy)]
pub(crate) struct PlaneFrame {
    /// Vertices shifted to the origin, `h' = (X − ox·W, Y − oy·W, W)`.
    pub hom: [Hom; 3],
    /// Normalisation of the plane coefficients (largest |coefficient| = 1); barycentrics
    /// do not depend on it.
    pub scale: f64,
    normals: [[f64; 3]; 3],
}

/// `None` for a triangle whose planes vanish or overflow (degenerate as seen from the
/// camera).
#[inline(always)]
pub(crate) fn plane_frame(verts: &[Hom; 3], origin: [i32; 2]) -> Option<PlaneFrame> {
    let (ox, oy) = (origin[0] as f64, origin[1] as f64);
    let hom = verts.map(|h| [h[0] - ox * h[2], h[1] - oy * h[2], h[2]]);
    let normals = [
        cross(&hom[1], &hom[2]),
        cross(&hom[2], &hom[0]),
        cross(&hom[0], &hom[1]),
    ];
    let largest = normals.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
    (largest > 0.0 && largest.is_finite()).then(|| PlaneFrame {
        hom,
        scale: 1.0 / largest,
        normals,
    })
}

impl<T: Real> TrianglePlanes<T> {
    /// Pixel centre of `(px, py)` relative to the origin.
    #[inline(always)]
    pub fn offset(&self, px: usize, py: usize) -> (T, T) {
        (
            T::c((px as i64 - self.origin[0] as i64) as f64 + 0.5),
            T::c((py as i64 - self.origin[1] as i64) as f64 + 0.5),
        )
    }

    /// Linear depth at barycentrics `l`; exactly the vertex depth for a triangle of
    /// constant depth (UV layouts, fronto-parallel planes), so such ties are exact.
    #[inline(always)]
    pub fn depth_at(&self, l: &[T; 3]) -> T {
        let d = &self.depth;
        d[0] + l[1] * (d[1] - d[0]) + l[2] * (d[2] - d[0])
    }

    /// A depth no pixel of the triangle can lie in front of: [`depth_at`](Self::depth_at)
    /// is a convex combination of the vertex depths up to rounding, the weights summing to
    /// 1 within a few ulps and each of its 6 operations rounding once, which moves it by
    /// less than 13·ε·max|d| below the nearest vertex; the margin is twice that. −∞ when a
    /// depth overflows `T` (never NaN), which skips nothing.
    #[inline(always)]
    pub fn depth_floor(&self) -> T {
        let d = &self.depth;
        let nearest = d[0].min(d[1]).min(d[2]);
        let largest = d[0].abs().max(d[1].abs()).max(d[2].abs());
        (nearest - T::c(32.0) * T::epsilon() * largest).max(T::neg_infinity())
    }

    /// Unnormalised barycentric weights at a pixel centre offset.
    #[inline(always)]
    pub fn raw(&self, ex: T, ey: T) -> [T; 3] {
        self.raw_on_row(ex, &self.row_terms(ey))
    }

    /// The row terms `c[i][1]·ey` of [`raw`](Self::raw) for a row at offset `ey`, made once
    /// for a scan along the row.
    #[inline(always)]
    pub fn row_terms(&self, ey: T) -> [T; 3] {
        map3(|i| self.coef[i][1] * ey)
    }

    /// [`raw`](Self::raw) at `(ex, ey)` given `row_terms(ey)`: the same operations in the
    /// same order, so the same bits.
    #[inline(always)]
    pub fn raw_on_row(&self, ex: T, row_terms: &[T; 3]) -> [T; 3] {
        let c = &self.coef;
        map3(|i| c[i][0] * ex + row_terms[i] + c[i][2])
    }
}

/// Barycentrics at one pixel: clamped to the simplex and normalised, with what the adjoint
/// needs.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Bary<T> {
    /// Clamped, normalised weights (sum to 1).
    pub lambda: [T; 3],
    /// Unclamped normalised weights `λ̃ / Σλ̃`.
    unclamped: [T; 3],
    inv_raw_sum: T,
    inv_clamped_sum: T,
}

/// The one function both passes use to turn plane values into barycentrics. `None` when
/// they are not finite (an edge-on triangle seen along its plane), which leaves the pixel
/// uncovered.
#[inline(always)]
pub(crate) fn barycentrics<T: Real>(raw: [T; 3]) -> Option<Bary<T>> {
    let inv_raw_sum = T::one() / (raw[0] + raw[1] + raw[2]);
    let unclamped = raw.map(|r| r * inv_raw_sum);
    // NaN-safe clamp: a NaN weight becomes 0 and then fails the sum test below.
    let clamped = unclamped.map(|x| if x > T::zero() { x } else { T::zero() });
    let sum = clamped[0] + clamped[1] + clamped[2];
    if !(sum > T::zero() && sum.is_finite()) {
        return None;
    }
    let inv_clamped_sum = T::one() / sum;
    Some(Bary {
        lambda: clamped.map(|x| x * inv_clamped_sum),
        unclamped,
        inv_raw_sum,
        inv_clamped_sum,
    })
}

/// Adjoint of [`barycentrics`]: the gradient of the raw plane values given the gradient
/// `g` of the clamped weights. A clamped weight passes no gradient.
#[inline(always)]
pub(crate) fn barycentrics_vjp<T: Real>(b: &Bary<T>, g: [T; 3]) -> [T; 3] {
    let g_dot = g[0] * b.lambda[0] + g[1] * b.lambda[1] + g[2] * b.lambda[2];
    let g_unclamped: [T; 3] = map3(|i| {
        if b.unclamped[i] > T::zero() {
            (g[i] - g_dot) * b.inv_clamped_sum
        } else {
            T::zero()
        }
    });
    let t =
        g_unclamped[0] * b.unclamped[0] + g_unclamped[1] * b.unclamped[1] + g_unclamped[2] * b.unclamped[2];
    g_unclamped.map(|x| (x - t) * b.inv_raw_sum)
}

/// A snapped (sub-)triangle to scan: three integer edge functions
/// `E(px, py) = a·px + b·py + c`, all ≥ 0 exactly on covered pixels (the top-left rule is
/// folded into `c`), and its pixel bounding box clamped to the viewport.
#[derive(Debug, Clone, Copy)]
pub(crate) struct CoverageTri {
    pub tri: u32,
    pub x0: u32,
    pub x1: u32,
    pub y0: u32,
    pub y1: u32,
    pub edges: [[i64; 3]; 3],
}

/// All triangles of a mesh after setup, kept in the fixed chunks they were set up in (no
/// concatenation copies): barycentric planes per input triangle (`None` for culled ones)
/// and the snapped sub-triangles to scan, in triangle order.
pub(crate) struct Setup<T> {
    chunks: Vec<SetupChunk<T>>,
}

struct SetupChunk<T> {
    planes: Vec<Option<TrianglePlanes<T>>>,
    coverage: Vec<CoverageTri>,
}

/// Where a sub-triangle is: `[chunk, index in chunk]`.
pub(crate) type CoverageRef = [u32; 2];

impl<T> Setup<T> {
    pub fn planes(&self, tri: usize) -> Option<&TrianglePlanes<T>> {
        self.chunks[tri / SETUP_CHUNK].planes[tri % SETUP_CHUNK].as_ref()
    }

    /// Every sub-triangle with its reference, in triangle order.
    pub fn coverage(&self) -> impl Iterator<Item = (CoverageRef, &CoverageTri)> {
        self.chunks.iter().enumerate().flat_map(|(k, c)| {
            c.coverage
                .iter()
                .enumerate()
                .map(move |(i, t)| ([k as u32, i as u32], t))
        })
    }

    pub fn coverage_at(&self, r: CoverageRef) -> &CoverageTri {
        &self.chunks[r[0] as usize].coverage[r[1] as usize]
    }
}

/// Sets up every face of `faces` (indices into `hom`, already validated), in parallel over
/// fixed chunks of faces.
pub(crate) fn setup_triangles<T: Real>(hom: &[Hom], faces: &[i32], vp: &Viewport) -> Setup<T> {
    let chunks = faces
        .par_chunks(3 * SETUP_CHUNK)
        .enumerate()
        .map(|(chunk, faces)| {
            let mut planes = Vec::with_capacity(faces.len() / 3);
            let mut coverage = Vec::with_capacity(faces.len() / 3);
            for (i, f) in faces.chunks_exact(3).enumerate() {
                let tri = (chunk * SETUP_CHUNK + i) as u32;
                // Gathered coordinate by coordinate: gathered as three `Hom`s, the vertices
                // went through the stack and were read back in wider loads than they were
                // stored with, which stalls (−0.07 and −0.09 ms a frame's raster, paired).
                let (a, b, c) = (&hom[f[0] as usize], &hom[f[1] as usize], &hom[f[2] as usize]);
                let verts = [[a[0], a[1], a[2]], [b[0], b[1], b[2]], [c[0], c[1], c[2]]];
                planes.push(setup_triangle(tri, &verts, vp, &mut coverage));
            }
            SetupChunk { planes, coverage }
        })
        .collect();
    Setup { chunks }
}

/// Clips, snaps and fans one triangle; pushes its sub-triangles to `coverage`. `None`
/// (nothing pushed) when it covers no pixel centre: fully clipped, degenerate after
/// snapping, or off-screen.
fn setup_triangle<T: Real>(
    tri: u32,
    verts: &[Hom; 3],
    vp: &Viewport,
    coverage: &mut Vec<CoverageTri>,
) -> Option<TrianglePlanes<T>> {
    // Fast path: nearly every triangle lies inside all clip planes. Its vertices and
    // three snapped corners stay in registers: a 32-corner array zeroed on the stack per
    // triangle, and the vertices stored there for `clip` and read back in wider loads
    // than they were stored with, had stalled the setup (2.2 → 1.2 ms for 14k faces).
    if verts
        .iter()
        .all(|h| (0..5).all(|p| clip_distance(h, p, vp) >= 0.0))
    {
        let fixed = verts.map(|h| snap(&h, vp));
        return setup_polygon(tri, verts, &fixed, vp, coverage);
    }
    // A copy, made only here, so the fast path never puts `verts` in memory.
    let poly = clip(&[verts[0], verts[1], verts[2]], vp);
    if poly.len < 3 {
        return None;
    }
    let mut fixed = [[0i64; 2]; MAX_POLY];
    for (f, h) in fixed.iter_mut().zip(&poly.verts[..poly.len]) {
        *f = snap(h, vp);
    }
    setup_polygon(tri, verts, &fixed[..poly.len], vp, coverage)
}

/// The planes of triangle `verts` and the fan of its snapped (clipped) polygon `fixed`
/// (3 corners or more).
#[inline(always)]
fn setup_polygon<T: Real>(
    tri: u32,
    verts: &[Hom; 3],
    fixed: &[[i64; 2]],
    vp: &Viewport,
    coverage: &mut Vec<CoverageTri>,
) -> Option<TrianglePlanes<T>> {
    let (x0, _, y0, _) = pixel_bbox(fixed, vp)?;
    let origin = [x0 as i32, y0 as i32];
    let frame = plane_frame(verts, origin)?;
    let planes = TrianglePlanes {
        coef: frame.normals.map(|n| n.map(|x| T::c(x * frame.scale))),
        depth: verts.map(|h| T::c(h[2])),
        origin,
    };
    let start = coverage.len();
    for i in 1..fixed.len() - 1 {
        if let Some(c) = coverage_triangle(tri, [fixed[0], fixed[i], fixed[i + 1]], vp) {
            coverage.push(c);
        }
    }
    (coverage.len() > start).then_some(planes)
}

#[inline(always)]
pub(crate) fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

struct Polygon {
    verts: [Hom; MAX_POLY],
    len: usize,
}

impl Polygon {
    fn push(&mut self, h: Hom) {
        // Unreachable capacity (see MAX_POLY); dropping a vertex would only shrink coverage.
        if self.len < MAX_POLY {
            self.verts[self.len] = h;
            self.len += 1;
        }
    }
}

/// Signed distance to clip plane `plane` (inside ≥ 0): the near plane, then the guard band.
#[inline(always)]
fn clip_distance(h: &Hom, plane: usize, vp: &Viewport) -> f64 {
    let [x, y, w] = *h;
    match plane {
        0 => w - vp.near,
        1 => x + GUARD_BAND_PX * w,
        2 => (vp.width as f64 + GUARD_BAND_PX) * w - x,
        3 => y + GUARD_BAND_PX * w,
        _ => (vp.height as f64 + GUARD_BAND_PX) * w - y,
    }
}

/// Sutherland–Hodgman against the five planes. New vertices are always computed from the
/// inside endpoint towards the outside one, so two triangles sharing an edge compute
/// bit-identical clipped endpoints (watertight clipping).
#[inline(never)]
fn clip(tri: &[Hom; 3], vp: &Viewport) -> Polygon {
    let mut poly = Polygon {
        verts: [[0.0; 3]; MAX_POLY],
        len: 3,
    };
    poly.verts[..3].copy_from_slice(tri);
    for plane in 0..5 {
        let mut dist = [0.0f64; MAX_POLY];
        let mut all_inside = true;
        for i in 0..poly.len {
            dist[i] = clip_distance(&poly.verts[i], plane, vp);
            all_inside &= dist[i] >= 0.0;
        }
        if all_inside {
            continue;
        }
        let mut out = Polygon {
            verts: [[0.0; 3]; MAX_POLY],
            len: 0,
        };
        for i in 0..poly.len {
            let j = if i + 1 == poly.len { 0 } else { i + 1 };
            let (a_in, b_in) = (dist[i] >= 0.0, dist[j] >= 0.0);
            if a_in {
                out.push(poly.verts[i]);
            }
            if a_in != b_in {
                out.push(if a_in {
                    intersect(&poly.verts[i], dist[i], &poly.verts[j], dist[j])
                } else {
                    intersect(&poly.verts[j], dist[j], &poly.verts[i], dist[i])
                });
            }
        }
        if out.len < 3 {
            out.len = 0;
            return out;
        }
        poly = out;
    }
    poly
}

#[inline(always)]
fn intersect(inside: &Hom, d_in: f64, outside: &Hom, d_out: f64) -> Hom {
    let t = d_in / (d_in - d_out);
    map3(|k| inside[k] + t * (outside[k] - inside[k]))
}

/// Projects a clipped vertex and snaps it to the sub-pixel grid.
#[inline(always)]
fn snap(h: &Hom, vp: &Viewport) -> [i64; 2] {
    let snap_axis = |v: f64, side: usize| {
        let (lo, hi) = (-GUARD_BAND_PX - 1.0, side as f64 + GUARD_BAND_PX + 1.0);
        // Clipping bounds the value up to rounding; clamp without letting NaN through.
        let v = if v >= lo { v.min(hi) } else { lo };
        (v * SUBPIXEL_SCALE).round() as i64
    };
    [
        snap_axis(h[0] / h[2], vp.width),
        snap_axis(h[1] / h[2], vp.height),
    ]
}

/// Inclusive range of pixels whose centres lie within `[lo, hi]` (sub-pixel units),
/// clamped to `[0, side)`.
fn pixel_range(lo: i64, hi: i64, side: usize) -> Option<(u32, u32)> {
    let s = 1i64 << SUBPIXEL_BITS;
    let first = -(-(lo - HALF_PIXEL)).div_euclid(s);
    let last = (hi - HALF_PIXEL).div_euclid(s);
    let (first, last) = (first.max(0), last.min(side as i64 - 1));
    (first <= last).then_some((first as u32, last as u32))
}

fn pixel_bbox(points: &[[i64; 2]], vp: &Viewport) -> Option<(u32, u32, u32, u32)> {
    let min_max = |axis: usize| {
        points.iter().fold((i64::MAX, i64::MIN), |(lo, hi), p| {
            (lo.min(p[axis]), hi.max(p[axis]))
        })
    };
    let (xl, xh) = min_max(0);
    let (yl, yh) = min_max(1);
    let (x0, x1) = pixel_range(xl, xh, vp.width)?;
    let (y0, y1) = pixel_range(yl, yh, vp.height)?;
    Some((x0, x1, y0, y1))
}

/// Integer edge functions of a snapped triangle, oriented so the interior is positive.
/// Top-left rule: a pixel centre exactly on an edge is covered only if the edge is a top
/// edge (horizontal, interior below) or a left edge (interior to its right), so of two
/// triangles sharing an edge exactly one covers it.
fn coverage_triangle(tri: u32, p: [[i64; 2]; 3], vp: &Viewport) -> Option<CoverageTri> {
    let area2 = (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]);
    if area2 == 0 {
        return None;
    }
    let p = if area2 > 0 { p } else { [p[0], p[2], p[1]] };
    let (x0, x1, y0, y1) = pixel_bbox(&p, vp)?;
    let s = 1i64 << SUBPIXEL_BITS;
    let edges = map3(|k| {
        let (a, b) = (p[k], p[(k + 1) % 3]);
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let top_left = dy < 0 || (dy == 0 && dx > 0);
        // E(s) = dx·(s.y − a.y) − dy·(s.x − a.x) at s = (px·S + S/2, py·S + S/2).
        [
            -dy * s,
            dx * s,
            (dx - dy) * HALF_PIXEL - dx * a[1] + dy * a[0] - i64::from(!top_left),
        ]
    });
    Some(CoverageTri {
        tri,
        x0,
        x1,
        y0,
        y1,
        edges,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vp(w: usize, h: usize) -> Viewport {
        Viewport {
            width: w,
            height: h,
            near: 0.0,
        }
    }

    /// Pixel centres covered by one snapped triangle, by brute force over the viewport.
    fn covered(tri: [Hom; 3], v: &Viewport) -> Vec<usize> {
        let mut cov = Vec::new();
        let planes = setup_triangle::<f64>(0, &tri, v, &mut cov);
        let mut out = Vec::new();
        if planes.is_none() {
            return out;
        }
        for c in &cov {
            for py in c.y0..=c.y1 {
                for px in c.x0..=c.x1 {
                    let e = c.edges.map(|e| e[0] * px as i64 + e[1] * py as i64 + e[2]);
                    if e.iter().all(|&x| x >= 0) {
                        out.push(py as usize * v.width + px as usize);
                    }
                }
            }
        }
        out
    }

    #[test]
    fn fan_around_a_vertex_on_a_pixel_centre_covers_it_once() {
        // Eight triangles around (4.5, 4.5), every vertex on a pixel centre.
        let v = vp(10, 10);
        let ring = [
            (6.5, 4.5),
            (6.5, 6.5),
            (4.5, 6.5),
            (2.5, 6.5),
            (2.5, 4.5),
            (2.5, 2.5),
            (4.5, 2.5),
            (6.5, 2.5),
        ];
        let mut count = vec![0; 100];
        for k in 0..8 {
            let (a, b) = (ring[k], ring[(k + 1) % 8]);
            // Alternate windings: coverage must not depend on orientation.
            let tri = if k % 2 == 0 {
                [[4.5, 4.5, 1.0], [a.0, a.1, 1.0], [b.0, b.1, 1.0]]
            } else {
                [[4.5, 4.5, 1.0], [b.0, b.1, 1.0], [a.0, a.1, 1.0]]
            };
            for p in covered(tri, &v) {
                count[p] += 1;
            }
        }
        for py in 2..=6 {
            for px in 2..=6 {
                let inner = (3..=5).contains(&px) && (3..=5).contains(&py);
                if inner {
                    assert_eq!(count[py * 10 + px], 1, "pixel ({px}, {py})");
                }
                assert!(count[py * 10 + px] <= 1, "pixel ({px}, {py}) covered twice");
            }
        }
    }

    #[test]
    fn barycentrics_are_clamped_and_sum_to_one() {
        let b = barycentrics([-1e-9f64, 0.5, 0.5]).unwrap();
        assert_eq!(b.lambda[0], 0.0);
        assert!((b.lambda.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        assert!(barycentrics([0.0f64, 0.0, 0.0]).is_none());
        assert!(barycentrics([f64::NAN, 1.0, 1.0]).is_none());
        assert!(barycentrics([f32::MAX, f32::MAX, 1.0]).is_none());
    }

    #[test]
    fn barycentric_adjoint_matches_finite_differences() {
        let raw = [0.3f64, 0.5, -0.05];
        let g = [0.7, -1.3, 0.4];
        let f = |r: [f64; 3]| {
            let b = barycentrics(r).unwrap();
            (0..3).map(|i| g[i] * b.lambda[i]).sum::<f64>()
        };
        let an = barycentrics_vjp(&barycentrics(raw).unwrap(), g);
        for k in 0..3 {
            let h = 1e-7;
            let (mut p, mut m) = (raw, raw);
            p[k] += h;
            m[k] -= h;
            let fd = (f(p) - f(m)) / (2.0 * h);
            assert!((fd - an[k]).abs() < 1e-7, "{k}: {fd} vs {}", an[k]);
        }
    }

    /// The scan skips a pixel whose stored depth is below the triangle's `depth_floor`, so
    /// no barycentrics may give a depth below it: weights at edges, corners and far outside
    /// (clamped), depths nearly equal and large, spread over decades, and behind the camera.
    #[test]
    fn no_pixel_lies_in_front_of_the_depth_floor() {
        fn check<T: Real>() {
            let mut rng = crate::testing::Rng::new(5);
            let depth_sets: Vec<[f64; 3]> = vec![
                [1_000.0, 1_000.000_1, 1_000.000_2],
                [0.75, 0.75, 0.75],
                [0.010_01, 99.9, 7.3],
                [-3.0, 0.5, 2.0],
                [1e-30, 1e30, 1.0],
            ];
            let mut checked = 0;
            for case in 0..4000 {
                let d = if case < depth_sets.len() * 400 {
                    depth_sets[case % depth_sets.len()]
                } else {
                    let scale = 10f64.powf(rng.uniform(-3.0, 4.0));
                    [0; 3].map(|_| scale * rng.uniform(0.5, 1.5))
                };
                let planes = TrianglePlanes::<T> {
                    coef: [[T::zero(); 3]; 3],
                    depth: d.map(T::c),
                    origin: [0, 0],
                };
                let floor = planes.depth_floor();
                // Weights from a corner (one near 1) to the middle, and some outside.
                let corner = rng.next_u64() as usize % 3;
                let raw: [f64; 3] = match case % 4 {
                    0 => map3(|k| {
                        if k == corner {
                            rng.uniform(0.1, 10.0)
                        } else {
                            rng.uniform(0.0, 1e-6)
                        }
                    }),
                    1 => [0; 3].map(|_| rng.uniform(0.0, 1.0)),
                    2 => [
                        rng.uniform(-1e-3, 0.0),
                        rng.uniform(0.0, 1.0),
                        rng.uniform(0.0, 1.0),
                    ],
                    _ => [0; 3].map(|_| rng.uniform(-0.5, 1.0)),
                };
                let Some(b) = barycentrics(raw.map(T::c)) else {
                    continue;
                };
                let z = planes.depth_at(&b.lambda);
                assert!(
                    z >= floor,
                    "depths {d:?}, raw {raw:?}: depth {z:?} below floor {floor:?}"
                );
                checked += 1;
            }
            assert!(checked > 3000, "{checked}");
            // Depths that overflow `T`: a floor below everything, never NaN.
            let huge = TrianglePlanes::<T> {
                coef: [[T::zero(); 3]; 3],
                depth: [T::c(1e300); 3],
                origin: [0, 0],
            };
            let floor = huge.depth_floor();
            assert!(floor == T::neg_infinity() || floor.is_finite(), "{floor:?}");
        }
        check::<f32>();
        check::<f64>();
    }

    #[test]
    fn clipping_keeps_the_part_in_front_of_the_near_plane() {
        let v = Viewport {
            width: 64,
            height: 64,
            near: 0.5,
        };
        // W goes from 1 to −1 along x: only the half with W ≥ 0.5 survives.
        let poly = clip(&[[0.0, 0.0, 1.0], [10.0, 0.0, -1.0], [0.0, 10.0, 1.0]], &v);
        assert_eq!(poly.len, 4);
        for i in 0..poly.len {
            assert!(poly.verts[i][2] >= 0.5 - 1e-12);
        }
        let behind = clip(&[[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -2.0]], &v);
        assert_eq!(behind.len, 0);
    }
}
