//! `antialias`: analytic antialiasing of silhouette edges, after nvdiffrast (Laine et al.
//! 2020, "Modular primitives for high-performance differentiable rendering"), giving the
//! image a gradient with respect to where silhouettes lie.
//!
//! For every pair of horizontally or vertically adjacent pixels with different triangle
//! ids, the nearer triangle (or the only one, against background) is examined along the
//! segment joining the two pixel centres. The triangle edge where that segment leaves it is
//! found; while that edge is not a silhouette edge, the segment is followed into the
//! neighbouring triangle across it (at most [`MAX_WALK`] triangles, never beyond the
//! segment, and not into the far pixel's own triangle: the surface runs on between them). nvdiffrast stops at the first triangle; near a silhouette, where triangles are
//! seen edge-on as slivers thinner than a pixel, the segment usually crosses several, and
//! stopping leaves most silhouette pixels hard (on a head at 256², mean |coverage − true
//! coverage| on the silhouette band 0.10 stopping, 0.06 walking; 4× supersampling 0.06).
//! A silhouette edge is open (boundary / non-manifold), or its neighbour lies on the same
//! side of it as seen from the camera. If the edge found is more perpendicular than
//! parallel to the segment and crosses at distance `d ∈ (−1/16, 1 + 1/16)` pixels from the
//! inside pixel centre (`d` clamped to [0, 1]), the two colours are blended:
//! `α = ±(0.5 − d)`; the inside pixel takes `α` of the outside colour when `d < 0.5`,
//! otherwise the outside pixel takes `d − 0.5` of the inside colour. The blend is
//! continuous as an edge sweeps across a pixel centre.
//!
//! Gradients: to the colours (linear) and to the two vertices of the crossing edge
//! through `d`, with the edge's extent across the segment guarded by `copysign(1e-3 px)`
//! and no position gradient where `|α| ≥ 0.5` (a clamped crossing). Triangles with a
//! vertex at depth `≤ near` are not antialiased and end a walk (their projection is not a
//! triangle). Pass the welded geometry faces: UV-split faces would make every seam a
//! silhouette.

use rayon::prelude::*;

use super::rasterize::camera_to_world_gradient;
use super::{check_faces, check_tri_id, TILE_ROWS};
use crate::camera::Camera;
use crate::error::{check_finite, check_indices, check_len, Error, Result};
use crate::mat3::map3;
use crate::memory::copied;
use crate::Real;

/// Crossings up to this far outside the segment (pixels) are accepted and clamped.
const CROSSING_TOLERANCE: f64 = 1.0 / 16.0;
/// Guard on the edge's extent across the segment in the gradient (pixels).
const GRADIENT_GUARD: f64 = 1e-3;
/// Triangles a pixel pair's segment is followed through in search of its silhouette edge.
pub const MAX_WALK: usize = 16;
/// Bit of [`Scene::silhouette`] set when the triangle projects (no vertex behind `near`).
const PROJECTS: u8 = 1 << 3;
/// Side of the square pixel blocks [`Scene::near_silhouette`] marks.
const BLOCK: usize = 8;
/// How far (pixels, per axis) a pair's first pixel centre can lie from the silhouette edge
/// point its blend crosses at: the crossing is within `1 + CROSSING_TOLERANCE` of the
/// inside pixel's centre, itself at most one pixel from the first's; rounded up for the
/// rounding of the crossing itself.
const SILHOUETTE_REACH: f64 = 3.0;

/// Gradients of [`antialias_backward`]; a field is `Some` exactly when it was asked for.
#[derive(Debug, Clone, Default)]
pub struct AntialiasGrads<T> {
    /// `(H, W, C)`
    pub v_color: Option<Vec<T>>,
    /// `(V, 3)`
    pub v_verts: Option<Vec<T>>,
}

/// Borrowed inputs shared by both passes.
pub struct AntialiasInputs<'a, T> {
    /// `(H, W, C)` colour to antialias.
    pub color: &'a [T],
    pub channels: usize,
    /// `(H, W)` from the rasterizer.
    pub tri_id: &'a [i32],
    /// `(H, W)` linear depth from the rasterizer.
    pub depth: &'a [T],
    /// `(V, 3)` world-space vertices the raster was made from.
    pub verts: &'a [T],
    /// `(F, 3)` welded geometry faces.
    pub faces: &'a [i32],
    /// `(F, 3)` from [`super::edge_topology`] for these faces.
    pub topology: &'a [i32],
    pub camera: &'a Camera,
}

/// Per-call geometry: projected vertices and per-triangle silhouette-edge masks.
struct Scene<'a, T> {
    width: usize,
    height: usize,
    tri_id: &'a [i32],
    depth: &'a [T],
    faces: &'a [i32],
    /// `(F, 3)`: the face across each edge, −1 for none.
    topology: &'a [i32],
    /// `(V, 3)`: pixel x, pixel y, camera depth.
    projected: Vec<[f64; 3]>,
    /// Bit k set when edge k (opposite vertex k) of the triangle is a silhouette edge;
    /// [`PROJECTS`] set when the triangle is in front of the near plane.
    silhouette: Vec<u8>,
    /// `(⌈H/BLOCK⌉, ⌈W/BLOCK⌉)`: whether a projected silhouette edge passes within
    /// [`SILHOUETTE_REACH`] of the block. Every blend crosses a silhouette edge on its
    /// segment, so pairs whose first pixel lies in an unmarked block are skipped without
    /// a walk — most of a mesh's interior, where neighbouring pixels see different
    /// triangles of one continuing surface; the decisions are the walk's own.
    near_silhouette: Vec<bool>,
    blocks_x: usize,
}

/// One antialiased pixel pair.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Blend {
    /// The pair: `p1` is right of / below `p0`.
    p0: usize,
    p1: usize,
    /// Weight of `color[p1] − color[p0]` added to the target pixel.
    alpha: f64,
    /// The crossing edge's vertices, and their positions relative to the inside pixel
    /// centre in the pair's frame (x along the pair, y across; swapped for vertical pairs).
    verts: [usize; 2],
    rel: [[f64; 2]; 2],
    vertical: bool,
}

impl Blend {
    fn target(&self) -> usize {
        if self.alpha > 0.0 {
            self.p0
        } else {
            self.p1
        }
    }
}

impl<'a, T: Real> AntialiasInputs<'a, T> {
    fn validate(&self) -> Result<(usize, usize, usize)> {
        let (w, h, c) = (
            self.camera.width as usize,
            self.camera.height as usize,
            self.channels,
        );
        if c == 0 {
            return Err(Error::Shape {
                arg: "color",
                expected: "(H, W, C) with C ≥ 1".into(),
                got: "C = 0".into(),
            });
        }
        check_len(
            "color",
            self.color,
            h * w * c,
            &format!("(H, W, C) = ({h}, {w}, {c})"),
        )?;
        if self.verts.len() % 3 != 0 {
            return Err(Error::Shape {
                arg: "verts",
                expected: "(V, 3)".into(),
                got: format!("{} elements", self.verts.len()),
            });
        }
        let num_verts = self.verts.len() / 3;
        let num_faces = check_faces("faces", self.faces, num_verts, "V")?;
        check_tri_id(self.tri_id, h, w, num_faces)?;
        check_len("depth", self.depth, h * w, &format!("(H, W) = ({h}, {w})"))?;
        check_len(
            "topology",
            self.topology,
            3 * num_faces,
            &format!("(F, 3) = ({num_faces}, 3)"),
        )?;
        check_indices("topology", self.topology, -1, num_faces as i64)?;
        check_finite("verts", self.verts)?;
        Ok((w, h, c))
    }

    /// The vertices in camera space, and projected: `(pixel x, pixel y, camera depth)`.
    fn projection(&self) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let cam = self.camera;
        let m = cam.viewmat.map(|row| row.map(|x| x as f64));
        let (fx, fy, cx, cy) = (cam.fx as f64, cam.fy as f64, cam.cx as f64, cam.cy as f64);
        let cam_space: Vec<[f64; 3]> = self
            .verts
            .chunks_exact(3)
            .map(|p| {
                let p = map3(|k| p[k].to_f64().unwrap_or(f64::NAN));
                map3(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3])
            })
            .collect();
        let projected = cam_space
            .iter()
            .map(|c| [fx * c[0] / c[2] + cx, fy * c[1] / c[2] + cy, c[2]])
            .collect();
        (cam_space, projected)
    }

    fn scene(&self) -> Scene<'a, T> {
        let cam = self.camera;
        let (cam_space, projected) = self.projection();
        let near = cam.near as f64;
        let silhouette: Vec<u8> = self
            .faces
            .par_chunks(3)
            .zip(self.topology.par_chunks(3))
            .map(|(f, across)| {
                let v = map3(|k| &cam_space[f[k] as usize]);
                if v.iter().any(|c| c[2] <= near || c[2].is_nan()) {
                    return 0u8;
                }
                let mut mask = PROJECTS;
                for k in 0..3 {
                    let (a, b) = (v[(k + 1) % 3], v[(k + 2) % 3]);
                    let silhouette = across[k] < 0 || {
                        // Sides of the plane through the camera centre and the edge.
                        let own = side(a, b, v[k]);
                        let other = side(a, b, &cam_space[third_vertex(self.faces, across[k], f)]);
                        let product = own * other;
                        product >= 0.0 || product.is_nan()
                    };
                    mask |= u8::from(silhouette) << k;
                }
                mask
            })
            .collect();
        let (width, height) = (cam.width as usize, cam.height as usize);
        let (blocks_x, near_silhouette) =
            mark_silhouette_blocks(width, height, self.faces, &projected, &silhouette);
        Scene {
            width,
            height,
            tri_id: self.tri_id,
            depth: self.depth,
            faces: self.faces,
            topology: self.topology,
            projected,
            silhouette,
            near_silhouette,
            blocks_x,
        }
    }
}

/// `(blocks per row, (⌈H/BLOCK⌉ × ⌈W/BLOCK⌉) marks)` of the pixel blocks within
/// [`SILHOUETTE_REACH`] of a projected silhouette edge's bounding box.
fn mark_silhouette_blocks(
    width: usize,
    height: usize,
    faces: &[i32],
    projected: &[[f64; 3]],
    silhouette: &[u8],
) -> (usize, Vec<bool>) {
    let (blocks_x, blocks_y) = (width.div_ceil(BLOCK), height.div_ceil(BLOCK));
    let mut marks = vec![false; blocks_x * blocks_y];
    // Pixel (x, y) has its centre at (x + 0.5, y + 0.5); the pixels whose centre lies in
    // [lo, hi] along an axis, clamped to the image, as a block range (None if empty).
    let blocks = |lo: f64, hi: f64, size: usize| {
        let first = (lo - 0.5).ceil().max(0.0);
        let last = (hi - 0.5).floor().min(size as f64 - 1.0);
        (first <= last).then_some((first as usize / BLOCK, last as usize / BLOCK))
    };
    for (face, &mask) in faces.chunks_exact(3).zip(silhouette) {
        if mask & PROJECTS == 0 || mask & !PROJECTS == 0 {
            continue;
        }
        for k in (0..3).filter(|k| mask & (1 << k) != 0) {
            let (a, b) = (
                &projected[face[(k + 1) % 3] as usize],
                &projected[face[(k + 2) % 3] as usize],
            );
            let (lo_x, hi_x) = (
                a[0].min(b[0]) - SILHOUETTE_REACH,
                a[0].max(b[0]) + SILHOUETTE_REACH,
            );
            let (lo_y, hi_y) = (
                a[1].min(b[1]) - SILHOUETTE_REACH,
                a[1].max(b[1]) + SILHOUETTE_REACH,
            );
            let (Some((x0, x1)), Some((y0, y1))) = (blocks(lo_x, hi_x, width), blocks(lo_y, hi_y, height))
            else {
                continue;
            };
            for row in marks[y0 * blocks_x..(y1 + 1) * blocks_x].chunks_exact_mut(blocks_x) {
                row[x0..=x1].fill(true);
            }
        }
    }
    (blocks_x, marks)
}

/// The vertex of face `other` that is not on the edge it shares with `face` (the edge's
/// two vertices are the ones `face` has in common with it).
fn third_vertex(faces: &[i32], other: i32, face: &[i32]) -> usize {
    let o = &faces[3 * other as usize..3 * other as usize + 3];
    *o.iter().find(|v| !face.contains(v)).unwrap_or(&o[0]) as usize
}

/// det(a, b, p): which side of the plane through the origin, `a` and `b` the point lies.
fn side(a: &[f64; 3], b: &[f64; 3], p: &[f64; 3]) -> f64 {
    p[0] * (a[1] * b[2] - a[2] * b[1])
        + p[1] * (a[2] * b[0] - a[0] * b[2])
        + p[2] * (a[0] * b[1] - a[1] * b[0])
}

impl<T: Real> Scene<'_, T> {
    /// Blends of the pairs owned by rows of `tile` (pairs to the right and below), in
    /// pixel order. Shared by forward and backward, so both make the same decisions.
    fn tile_blends(&self, tile: usize) -> Vec<Blend> {
        let (w, h) = (self.width, self.height);
        let mut out = Vec::new();
        for y in tile * TILE_ROWS..((tile + 1) * TILE_ROWS).min(h) {
            let marks = &self.near_silhouette[(y / BLOCK) * self.blocks_x..][..self.blocks_x];
            for x in 0..w {
                if !marks[x / BLOCK] {
                    continue;
                }
                let p = y * w + x;
                if x + 1 < w {
                    out.extend(self.blend(p, p + 1, x, y, false));
                }
                if y + 1 < h {
                    out.extend(self.blend(p, p + w, x, y, true));
                }
            }
        }
        out
    }

    fn blend(&self, p0: usize, p1: usize, x: usize, y: usize, vertical: bool) -> Option<Blend> {
        let (t0, t1) = (self.tri_id[p0], self.tri_id[p1]);
        if t0 == t1 {
            return None;
        }
        let first_inside = if t0 < 0 {
            false
        } else if t1 < 0 {
            true
        } else {
            let (d0, d1) = (self.depth[p0], self.depth[p1]);
            d0 < d1 || (d0 == d1 && t0 < t1)
        };
        let (ix, iy) = if first_inside {
            (x, y)
        } else if vertical {
            (x, y + 1)
        } else {
            (x + 1, y)
        };
        let centre = [ix as f64 + 0.5, iy as f64 + 0.5];
        let dir = if first_inside { 1.0 } else { -1.0 };
        let mut tri = if first_inside { t0 } else { t1 } as usize;
        // The far pixel's own triangle: reaching it across non-silhouette edges means the
        // surface runs on between the two centres (the common case inside a mesh).
        let far = if first_inside { t1 } else { t0 };
        let (f, k, d, a, b) = 'walk: {
            for _ in 0..MAX_WALK {
                let mask = self.silhouette[tri];
                if mask & PROJECTS == 0 {
                    return None;
                }
                let f = &self.faces[3 * tri..3 * tri + 3];
                // Frame: origin at the inside pixel centre, x along the pair, y across it.
                let rel = map3(|k| {
                    let q = &self.projected[f[k] as usize];
                    let (dx, dy) = (q[0] - centre[0], q[1] - centre[1]);
                    if vertical {
                        [dy, dx]
                    } else {
                        [dx, dy]
                    }
                });
                // Distance along the pair direction at which each crossing edge leaves the
                // triangle; the exit edge is the farthest crossing.
                let mut exit: Option<(usize, f64)> = None;
                for k in 0..3 {
                    let (a, b) = (rel[(k + 1) % 3], rel[(k + 2) % 3]);
                    if (a[1] < 0.0) == (b[1] < 0.0) {
                        continue;
                    }
                    let crossing = dir * (a[0] * b[1] - b[0] * a[1]) / (b[1] - a[1]);
                    if exit.is_none_or(|(_, d)| crossing > d) {
                        exit = Some((k, crossing));
                    }
                }
                let (k, d) = exit?;
                if mask & (1 << k) != 0 {
                    break 'walk (f, k, d, rel[(k + 1) % 3], rel[(k + 2) % 3]);
                }
                let next = self.topology[3 * tri + k];
                if next < 0 || next == far || d >= 1.0 + CROSSING_TOLERANCE {
                    return None;
                }
                tri = next as usize;
            }
            return None;
        };
        let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
        let accept = ey.abs() >= ex.abs() && d > -CROSSING_TOLERANCE && d < 1.0 + CROSSING_TOLERANCE;
        if !accept {
            return None;
        }
        let alpha = dir * (0.5 - d.clamp(0.0, 1.0));
        (alpha != 0.0).then_some(Blend {
            p0,
            p1,
            alpha,
            verts: [f[(k + 1) % 3] as usize, f[(k + 2) % 3] as usize],
            rel: [a, b],
            vertical,
        })
    }

    fn all_blends(&self) -> Vec<Vec<Blend>> {
        // A task per band: the silhouette's pairs sit in a few of them (−0.12 ms of 1.7,
        // faster in 193 of 200, a 512² frame's antialias alone).
        (0..self.height.div_ceil(TILE_ROWS))
            .into_par_iter()
            .with_max_len(1)
            .map(|tile| self.tile_blends(tile))
            .collect()
    }
}

/// The pixel pairs a forward pass blended, in its order: the decisions its backward would
/// make again from the same inputs. A training step keeps them from the forward, so the
/// pixel pairs are searched (and silhouettes walked) once instead of twice.
#[derive(Debug, Clone, PartialEq)]
pub struct SilhouetteBlends(Vec<Blend>);

/// Floats a blend takes in [`SilhouetteBlends::packed`].
pub const PACKED_BLEND: usize = 10;

impl SilhouetteBlends {
    pub fn len(&self) -> usize {
        self.0.len()
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// `(B, 10)` float64: `p0, p1`, the edge's two vertices, `vertical` (0 or 1), `alpha`,
    /// then the two vertices' positions in the pair's frame (4); indices are exact in f64.
    pub fn packed(&self) -> Vec<f64> {
        self.0
            .iter()
            .flat_map(|b| {
                let [a, c] = b.rel;
                [
                    b.p0 as f64,
                    b.p1 as f64,
                    b.verts[0] as f64,
                    b.verts[1] as f64,
                    f64::from(u8::from(b.vertical)),
                    b.alpha,
                    a[0],
                    a[1],
                    c[0],
                    c[1],
                ]
            })
            .collect()
    }

    /// Blends from [`Self::packed`], checked against an image of `pixels` pixels and
    /// `num_verts` vertices (any index out of range, or not a whole number, is an error,
    /// so nothing is read out of bounds).
    pub fn from_packed(packed: &[f64], pixels: usize, num_verts: usize) -> Result<Self> {
        let bad = |reason: String| Error::Invalid {
            arg: "blends",
            reason,
        };
        if packed.len() % PACKED_BLEND != 0 {
            return Err(bad(format!(
                "must be (B, {PACKED_BLEND}), got {} floats",
                packed.len()
            )));
        }
        let index = |x: f64, high: usize, what: &str, row: usize| {
            if x >= 0.0 && x < high as f64 && x.fract() == 0.0 {
                Ok(x as usize)
            } else {
                Err(bad(format!("row {row}: {what} {x} is not an index below {high}")))
            }
        };
        packed
            .chunks_exact(PACKED_BLEND)
            .enumerate()
            .map(|(row, b)| {
                let vertical = match b[4] {
                    0.0 => false,
                    1.0 => true,
                    x => return Err(bad(format!("row {row}: vertical must be 0 or 1, got {x}"))),
                };
                Ok(Blend {
                    p0: index(b[0], pixels, "pixel", row)?,
                    p1: index(b[1], pixels, "pixel", row)?,
                    alpha: b[5],
                    verts: [
                        index(b[2], num_verts, "vertex", row)?,
                        index(b[3], num_verts, "vertex", row)?,
                    ],
                    rel: [[b[6], b[7]], [b[8], b[9]]],
                    vertical,
                })
            })
            .collect::<Result<Vec<_>>>()
            .map(Self)
    }
}

/// Antialiased copy of `inputs.color`, `(H, W, C)`.
pub fn antialias_forward<T: Real>(inputs: &AntialiasInputs<T>) -> Result<Vec<T>> {
    Ok(antialias_forward_blends(inputs)?.0)
}

/// [`antialias_forward`] and the blends it made, for [`antialias_backward_blends`].
pub fn antialias_forward_blends<T: Real>(inputs: &AntialiasInputs<T>) -> Result<(Vec<T>, SilhouetteBlends)> {
    let (_, _, c) = inputs.validate()?;
    let scene = inputs.scene();
    let blends: Vec<Blend> = scene.all_blends().into_iter().flatten().collect();
    let color = inputs.color;
    let mut out = copied("antialiased image", color)?;
    for b in &blends {
        let t = b.target();
        let alpha = T::c(b.alpha);
        for k in 0..c {
            out[t * c + k] += alpha * (color[b.p1 * c + k] - color[b.p0 * c + k]);
        }
    }
    Ok((out, SilhouetteBlends(blends)))
}

/// Adjoint of [`antialias_forward`] given `v_out (H, W, C)`.
pub fn antialias_backward<T: Real>(
    inputs: &AntialiasInputs<T>,
    v_out: &[T],
    need_color: bool,
    need_verts: bool,
) -> Result<AntialiasGrads<T>> {
    let dims = inputs.validate()?;
    let scene = inputs.scene();
    let blends = SilhouetteBlends(scene.all_blends().into_iter().flatten().collect());
    backward(
        inputs,
        dims,
        &scene.projected,
        v_out,
        need_color,
        need_verts,
        &blends,
    )
}

/// [`antialias_backward`] with the `blends` its forward made on the same inputs
/// ([`antialias_forward_blends`]): the same gradients, bit for bit, without searching the
/// pixel pairs again.
pub fn antialias_backward_blends<T: Real>(
    inputs: &AntialiasInputs<T>,
    v_out: &[T],
    need_color: bool,
    need_verts: bool,
    blends: &SilhouetteBlends,
) -> Result<AntialiasGrads<T>> {
    let dims = inputs.validate()?;
    let (_, projected) = inputs.projection();
    backward(inputs, dims, &projected, v_out, need_color, need_verts, blends)
}

/// Both backward entry points after validating `inputs` (image `(w, h, c)`), with the
/// vertices' `projected` positions ([`AntialiasInputs::projection`]).
fn backward<T: Real>(
    inputs: &AntialiasInputs<T>,
    (w, h, c): (usize, usize, usize),
    projected: &[[f64; 3]],
    v_out: &[T],
    need_color: bool,
    need_verts: bool,
    blends: &SilhouetteBlends,
) -> Result<AntialiasGrads<T>> {
    check_len("v_out", v_out, h * w * c, &format!("(H, W, C) = ({h}, {w}, {c})"))?;
    let num_verts = inputs.verts.len() / 3;
    if let Some(b) = blends
        .0
        .iter()
        .find(|b| b.p0.max(b.p1) >= h * w || b.verts[0].max(b.verts[1]) >= num_verts)
    {
        return Err(Error::Invalid {
            arg: "blends",
            reason: format!(
                "a blend of pixels {}, {} and vertices {:?} is outside the image or the mesh",
                b.p0, b.p1, b.verts
            ),
        });
    }
    let blends = &blends.0;
    let color = inputs.color;
    let v_color = need_color
        .then(|| -> Result<Vec<T>> {
            let mut v_color = copied("color gradient", v_out)?;
            for b in blends {
                let t = b.target();
                let alpha = T::c(b.alpha);
                for k in 0..c {
                    let g = alpha * v_out[t * c + k];
                    v_color[b.p0 * c + k] -= g;
                    v_color[b.p1 * c + k] += g;
                }
            }
            Ok(v_color)
        })
        .transpose()?;
    let v_verts = need_verts.then(|| {
        let cam = inputs.camera;
        let (fx, fy, cx, cy) = (cam.fx as f64, cam.fy as f64, cam.cx as f64, cam.cy as f64);
        let mut v_cam = vec![0.0f64; inputs.verts.len()];
        for b in blends {
            if b.alpha.abs() >= 0.5 {
                continue;
            }
            let t = b.target();
            let mut dd = 0.0f64;
            for k in 0..c {
                let diff = color[b.p1 * c + k] - color[b.p0 * c + k];
                dd += (v_out[t * c + k] * diff).to_f64().unwrap_or(0.0);
            }
            if dd == 0.0 {
                continue;
            }
            // α = ±0.5 − x_c with x_c = (a.x·b.y − b.x·a.y)/(b.y − a.y) in the pair frame.
            let [a, bb] = b.rel;
            let ey = bb[1] - a[1];
            let inv = 1.0 / (ey + GRADIENT_GUARD.copysign(ey));
            let xc = (a[0] * bb[1] - bb[0] * a[1]) * inv;
            let g = -dd;
            let frame = [
                [g * bb[1] * inv, g * (xc - bb[0]) * inv],
                [-g * a[1] * inv, g * (a[0] - xc) * inv],
            ];
            for (v, gf) in b.verts.iter().zip(frame) {
                let (gx, gy) = if b.vertical {
                    (gf[1], gf[0])
                } else {
                    (gf[0], gf[1])
                };
                let q = &projected[*v];
                let z = q[2];
                v_cam[3 * v] += gx * fx / z;
                v_cam[3 * v + 1] += gy * fy / z;
                v_cam[3 * v + 2] -= (gx * (q[0] - cx) + gy * (q[1] - cy)) / z;
            }
        }
        camera_to_world_gradient(&v_cam, cam)
    });
    Ok(AntialiasGrads { v_color, v_verts })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{edge_topology, rasterize_forward};
    use crate::testing::sphere;

    /// Skipping the pairs of blocks no silhouette edge reaches changes no decision: the
    /// blends are those of a search of every pair, on a smooth sphere (silhouette only at
    /// its outline: most blocks skipped) and a jittered one (folds all over it).
    #[test]
    fn skipping_blocks_far_from_silhouettes_keeps_every_blend() {
        let k = [[90.0, 0.0, 60.3], [0.0, 92.0, 57.6], [0.0, 0.0, 1.0]];
        let view = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let cam = Camera::new(k, view, 120, 112, 0.01, 100.0).unwrap();
        for (jitter, most_skipped) in [(0.0, true), (0.01, false)] {
            let (verts, faces) = sphere(40, 60, jitter, 5);
            let topology = edge_topology(&faces, verts.len() / 3).unwrap();
            let raster = rasterize_forward(&verts, &faces, &cam).unwrap();
            let color = vec![0.5f64; 120 * 112];
            let inputs = AntialiasInputs {
                color: &color,
                channels: 1,
                tri_id: &raster.tri_id,
                depth: &raster.depth,
                verts: &verts,
                faces: &faces,
                topology: &topology,
                camera: &cam,
            };
            let mut scene = inputs.scene();
            let skipped = scene.near_silhouette.iter().filter(|&&m| !m).count();
            let blends = scene.all_blends();
            scene.near_silhouette.fill(true);
            let searched = scene.all_blends();
            assert_eq!(blends, searched, "jitter {jitter}");
            assert!(
                blends.iter().map(Vec::len).sum::<usize>() > 100,
                "jitter {jitter}"
            );
            if most_skipped {
                assert!(
                    2 * skipped > scene.near_silhouette.len(),
                    "{skipped} blocks skipped"
                );
            }
        }
    }
}
