//! The triangle BVH: obvhs' compressed wide BVH8, built once and refit in place when the
//! triangles move but their number does not (an animated mesh of fixed topology).
//!
//! A refit keeps the tree (which triangles share a leaf, which nodes share a parent) and
//! recomputes every node's bounds from the current triangles, children before parents,
//! quantised exactly as obvhs' builder quantises them. Bounds are then conservative for
//! any triangles whatsoever, so traversal stays exact; only its speed depends on how well
//! the tree's grouping suits the new shape. Refitting to the triangles the tree was built
//! from reproduces the built nodes bit for bit.

use std::time::Duration;

use glam::Vec3A;
use obvhs::aabb::Aabb;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;
use rayon::prelude::*;

use super::intersect::{intersect_edges, triangle_edges, EdgeTri, TriHit};
use crate::error::{check_finite, check_indices, check_len, Error, Result};

/// A triangle as three corner positions.
pub type Tri = [[f32; 3]; 3];

/// Largest grid coordinate of obvhs' 8-bit child bounds.
const QUANT_MAX: f32 = 255.0;

/// A compressed wide BVH over a fixed number of triangles, with the triangles it
/// traverses; see the module docs.
#[derive(Clone, Debug)]
pub struct TriangleBvh {
    cwbvh: CwBvh,
    /// The triangles in the tree's primitive order (`ordered[i]` is triangle
    /// `primitive_indices[i]`), so a leaf's triangles sit side by side in memory, as
    /// corner and edges ready for the intersection test.
    ordered: Vec<EdgeTri>,
    /// Node indices by depth (the root alone first): a refit's order, deepest first.
    levels: Vec<Vec<u32>>,
}

impl TriangleBvh {
    /// Builds the tree over `tris` (single-threaded, so the same triangles always give
    /// the same tree). obvhs' medium preset: ~10 % slower to build than its fast one for
    /// ~5 % faster traversal (a kept tree is built rarely), and no spatial splits, whose
    /// clipped bounds a refit could not keep.
    pub fn build(tris: &[Tri]) -> Self {
        if tris.is_empty() {
            return Self {
                cwbvh: CwBvh::default(),
                ordered: Vec::new(),
                levels: Vec::new(),
            };
        }
        let triangles: Vec<Triangle> = tris
            .iter()
            .map(|t| Triangle {
                v0: t[0].into(),
                v1: t[1].into(),
                v2: t[2].into(),
            })
            .collect();
        let cwbvh = build_cwbvh_from_tris(
            &triangles,
            BvhBuildParams::medium_build(),
            &mut Duration::default(),
        );
        let levels = levels(&cwbvh);
        let ordered = cwbvh
            .primitive_indices
            .iter()
            .map(|&p| triangle_edges(&tris[p as usize]))
            .collect();
        Self {
            cwbvh,
            ordered,
            levels,
        }
    }

    /// Builds the tree over a mesh: `vertices` (V, 3) and `faces` (F, 3), validated first
    /// (errors name the argument).
    pub fn from_mesh(vertices: &[f32], faces: &[i32]) -> Result<Self> {
        Ok(Self::build(&mesh_triangles(vertices, faces)?))
    }

    /// Number of triangles the tree was built over (and every refit must give).
    pub fn num_tris(&self) -> usize {
        self.ordered.len()
    }

    /// The closest hit along `origin + t·dir` (unit `dir`) with `t` in `(t_min, t_max)`:
    /// (triangle index, hit). Ties keep the first triangle the traversal meets.
    pub fn closest_hit(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
    ) -> Option<(usize, TriHit)> {
        if self.ordered.is_empty() {
            return None;
        }
        let ray = Ray::new(origin.into(), dir.into(), t_min, t_max);
        let mut hit = RayHit::none();
        let mut best: Option<(usize, TriHit)> = None;
        self.cwbvh.ray_traverse(ray, &mut hit, |r, id| {
            match intersect_edges(origin, dir, &self.ordered[id], t_min, r.tmax) {
                Some(h) => {
                    best = Some((id, h));
                    h.t
                }
                None => f32::INFINITY,
            }
        });
        best.map(|(id, h)| (self.cwbvh.primitive_indices[id] as usize, h))
    }

    /// Whether any triangle lies along `origin + t·dir` for `t` in `(t_min, t_max)`.
    pub fn occluded(&self, origin: [f32; 3], dir: [f32; 3], t_min: f32, t_max: f32) -> bool {
        if self.ordered.is_empty() {
            return false;
        }
        let ray = Ray::new(origin.into(), dir.into(), t_min, t_max);
        !self.cwbvh.ray_traverse_miss(ray, |_, id| {
            intersect_edges(origin, dir, &self.ordered[id], t_min, t_max).map_or(f32::INFINITY, |h| h.t)
        })
    }

    /// Moves the bounds to `tris` (the same number of triangles as the build, in the same
    /// order). Errors, before changing anything, when the count differs.
    pub fn refit(&mut self, tris: &[Tri]) -> Result<()> {
        if tris.len() != self.ordered.len() {
            return Err(Error::Invalid {
                arg: "bvh",
                reason: format!(
                    "was built over {} triangles, cannot be refit to {}",
                    self.ordered.len(),
                    tris.len()
                ),
            });
        }
        if tris.is_empty() {
            return Ok(());
        }
        let bvh = &mut self.cwbvh;
        self.ordered
            .par_iter_mut()
            .zip(bvh.primitive_indices.par_iter())
            .for_each(|(slot, &p)| *slot = triangle_edges(&tris[p as usize]));
        // Deepest level first; the nodes of a level only read the bounds of deeper ones.
        let mut bounds = vec![Aabb::empty(); bvh.nodes.len()];
        for level in self.levels.iter().rev() {
            let refit: Vec<(CwBvhNode, Aabb)> = level
                .par_iter()
                .map(|&n| refit_node(bvh.nodes[n as usize], &bounds, &bvh.primitive_indices, tris))
                .collect();
            for (&n, (node, node_bounds)) in level.iter().zip(refit) {
                bvh.nodes[n as usize] = node;
                bounds[n as usize] = node_bounds;
            }
        }
        bvh.total_aabb = bounds[0];
        Ok(())
    }
}

/// The corner positions of every face, after checking shapes, finiteness and indices.
pub fn mesh_triangles(vertices: &[f32], faces: &[i32]) -> Result<Vec<Tri>> {
    let (nv, nf) = (vertices.len() / 3, faces.len() / 3);
    if nv > MAX_ELEMENTS || nf > MAX_ELEMENTS {
        return Err(Error::TooLarge {
            what: "scene vertices/faces",
            requested: nv.max(nf) as u128,
            limit: MAX_ELEMENTS as u128,
        });
    }
    check_len("vertices", vertices, nv * 3, "(V, 3)")?;
    check_len("faces", faces, nf * 3, "(F, 3)")?;
    check_finite("vertices", vertices)?;
    check_indices("faces", faces, 0, nv as i64)?;
    let vert = |i: i32| {
        let i = i as usize * 3;
        [vertices[i], vertices[i + 1], vertices[i + 2]]
    };
    Ok(faces
        .chunks_exact(3)
        .map(|f| [vert(f[0]), vert(f[1]), vert(f[2])])
        .collect())
}

/// Largest accepted vertex or face count (index arithmetic stays in u32).
pub const MAX_ELEMENTS: usize = 1 << 30;

/// `node` with its child bounds recomputed from `bounds` (its internal children's, already
/// refit) and its leaves' triangles; and its own bounds.
fn refit_node(
    mut node: CwBvhNode,
    bounds: &[Aabb],
    primitive_indices: &[u32],
    tris: &[Tri],
) -> (CwBvhNode, Aabb) {
    let mut child_bounds = [None; 8];
    let mut internal_rank = 0;
    for (slot, &meta) in node.child_meta.iter().enumerate() {
        if meta == 0 {
            continue; // empty slot
        }
        child_bounds[slot] = Some(if node.imask & (1 << slot) != 0 {
            let child = node.child_base_idx as usize + internal_rank;
            internal_rank += 1;
            bounds[child]
        } else {
            // Leaf: offset in the low 5 bits, count in unary in the high 3.
            let first = node.primitive_base_idx as usize + (meta & 0b1_1111) as usize;
            let count = (meta >> 5).count_ones() as usize;
            primitive_indices[first..first + count]
                .iter()
                .fold(Aabb::empty(), |b, &p| b.union(&tri_bounds(&tris[p as usize])))
        });
    }
    let node_bounds = child_bounds
        .iter()
        .flatten()
        .fold(Aabb::empty(), |a, b| a.union(b));
    // obvhs' quantisation: a power-of-two cell per axis so 255 cells span the node.
    let p = node_bounds.min;
    let e = ((node_bounds.max - node_bounds.min).max(Vec3A::splat(1e-20)) * (1.0 / QUANT_MAX))
        .log2()
        .ceil()
        .exp2();
    let rcp_e = 1.0 / e;
    node.p = p.into();
    node.e = [e.x, e.y, e.z].map(|c| (c.to_bits() >> 23) as u8);
    for (slot, b) in child_bounds.iter().enumerate() {
        let Some(b) = b else { continue };
        let lo = ((b.min - p) * rcp_e)
            .floor()
            .clamp(Vec3A::ZERO, Vec3A::splat(QUANT_MAX));
        let hi = ((b.max - p) * rcp_e)
            .ceil()
            .clamp(Vec3A::ZERO, Vec3A::splat(QUANT_MAX));
        node.child_min_x[slot] = lo.x as u8;
        node.child_min_y[slot] = lo.y as u8;
        node.child_min_z[slot] = lo.z as u8;
        node.child_max_x[slot] = hi.x as u8;
        node.child_max_y[slot] = hi.y as u8;
        node.child_max_z[slot] = hi.z as u8;
    }
    (node, node_bounds)
}

fn tri_bounds(t: &Tri) -> Aabb {
    let (a, b, c) = (Vec3A::from(t[0]), Vec3A::from(t[1]), Vec3A::from(t[2]));
    Aabb {
        min: a.min(b).min(c),
        max: a.max(b).max(c),
    }
}

/// The nodes grouped by depth, root first.
fn levels(bvh: &CwBvh) -> Vec<Vec<u32>> {
    let mut levels = vec![vec![0u32]];
    loop {
        let next: Vec<u32> = levels[levels.len() - 1]
            .iter()
            .flat_map(|&n| {
                let node = &bvh.nodes[n as usize];
                (0..node.imask.count_ones()).map(move |rank| node.child_base_idx + rank)
            })
            .collect();
        if next.is_empty() {
            return levels;
        }
        levels.push(next);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;

    fn soup(rng: &mut Rng, n: usize, spread: f32) -> Vec<Tri> {
        (0..n)
            .map(|_| {
                let c = [0, 1, 2].map(|_| rng.uniform(-1.0, 1.0) as f32);
                [0, 1, 2].map(|_| [0, 1, 2].map(|k| c[k] + spread * rng.uniform(-1.0, 1.0) as f32))
            })
            .collect()
    }

    #[test]
    fn refit_to_the_build_triangles_gives_the_built_nodes() {
        let tris = soup(&mut Rng::new(1), 3000, 0.05);
        let built = TriangleBvh::build(&tris);
        let mut refit = TriangleBvh::build(&soup(&mut Rng::new(1), 3000, 0.05));
        refit.refit(&soup(&mut Rng::new(9), 3000, 0.2)).unwrap();
        assert_ne!(refit.cwbvh.nodes, built.cwbvh.nodes);
        refit.refit(&tris).unwrap();
        assert_eq!(refit.cwbvh.nodes, built.cwbvh.nodes);
        assert_eq!(refit.cwbvh.total_aabb, built.cwbvh.total_aabb);
        assert_eq!(
            refit.levels.iter().map(Vec::len).sum::<usize>(),
            built.cwbvh.nodes.len()
        );
    }

    #[test]
    fn refit_refuses_another_triangle_count() {
        let mut bvh = TriangleBvh::build(&soup(&mut Rng::new(2), 50, 0.1));
        let err = bvh.refit(&soup(&mut Rng::new(2), 49, 0.1)).unwrap_err();
        assert!(matches!(err, Error::Invalid { arg: "bvh", .. }), "{err}");
    }
}
