//! Ray–triangle intersection (Möller–Trumbore), returning the distance and the
//! barycentrics the shading and the outputs use.

/// A hit on one triangle: distance along the (unit) ray, barycentrics `(u, v)` of vertices
/// 1 and 2 (vertex 0 has `1 − u − v`), as in nvdiffrast's rasterizer output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriHit {
    pub t: f32,
    pub u: f32,
    pub v: f32,
}

#[inline]
pub fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
pub fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The closest intersection of the ray `origin + t·dir` with the triangle `p`, for `t` in
/// the open interval `(t_min, t_max)`, both faces counted. Edges are inclusive (a ray
/// through a shared edge hits at least one of its triangles up to rounding). Degenerate
/// triangles (zero area, or a ray in their plane) are never hit. NaN-safe: every test is
/// written so that NaN fails it.
#[inline]
pub fn intersect_triangle(
    origin: [f32; 3],
    dir: [f32; 3],
    p: &[[f32; 3]; 3],
    t_min: f32,
    t_max: f32,
) -> Option<TriHit> {
    intersect_edges(origin, dir, &triangle_edges(p), t_min, t_max)
}

/// A triangle as its first corner and the edges to the other two, `[p0, p1 − p0,
/// p2 − p0]`: what the intersection test needs, precomputed once per frame.
pub type EdgeTri = [[f32; 3]; 3];

#[inline]
pub fn triangle_edges(p: &[[f32; 3]; 3]) -> EdgeTri {
    [p[0], sub(p[1], p[0]), sub(p[2], p[0])]
}

/// [`intersect_triangle`] on a triangle given by [`triangle_edges`] (the same result).
#[inline]
pub fn intersect_edges(
    origin: [f32; 3],
    dir: [f32; 3],
    tri: &EdgeTri,
    t_min: f32,
    t_max: f32,
) -> Option<TriHit> {
    let [p0, e1, e2] = *tri;
    let pvec = cross(dir, e2);
    let det = dot(e1, pvec);
    if !(det != 0.0 && det.is_finite()) {
        return None;
    }
    let inv = 1.0 / det;
    let tvec = sub(origin, p0);
    let u = dot(tvec, pvec) * inv;
    if !((0.0..=1.0).contains(&u)) {
        return None;
    }
    let qvec = cross(tvec, e1);
    let v = dot(dir, qvec) * inv;
    if !(v >= 0.0 && u + v <= 1.0) {
        return None;
    }
    let t = dot(e2, qvec) * inv;
    if !(t > t_min && t < t_max) {
        return None;
    }
    Some(TriHit { t, u, v })
}

#[cfg(test)]
mod tests {
    use super::*;

    const TRI: [[f32; 3]; 3] = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]];

    #[test]
    fn hits_with_barycentrics_of_vertices_one_and_two() {
        let h = intersect_triangle([0.25, 0.5, 0.0], [0.0, 0.0, 1.0], &TRI, 0.0, 10.0).unwrap();
        assert_eq!(
            h,
            TriHit {
                t: 1.0,
                u: 0.25,
                v: 0.5
            }
        );
        // Back face counts too.
        let h = intersect_triangle([0.25, 0.5, 2.0], [0.0, 0.0, -1.0], &TRI, 0.0, 10.0).unwrap();
        assert_eq!(h.t, 1.0);
    }

    #[test]
    fn misses_outside_behind_and_beyond() {
        let d = [0.0, 0.0, 1.0];
        assert!(intersect_triangle([0.6, 0.6, 0.0], d, &TRI, 0.0, 10.0).is_none());
        assert!(intersect_triangle([0.2, 0.2, 2.0], d, &TRI, 0.0, 10.0).is_none());
        assert!(intersect_triangle([0.2, 0.2, 0.0], d, &TRI, 0.0, 0.5).is_none());
    }

    #[test]
    fn degenerate_and_nan_never_hit() {
        let flat = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]];
        assert!(intersect_triangle([0.5, 0.0, 0.0], [0.0, 0.0, 1.0], &flat, 0.0, 10.0).is_none());
        let nan = [f32::NAN, 0.0, 1.0];
        assert!(intersect_triangle([0.2, 0.2, 0.0], nan, &TRI, 0.0, 10.0).is_none());
        // A ray in the triangle's plane.
        assert!(intersect_triangle([-1.0, 0.2, 1.0], [1.0, 0.0, 0.0], &TRI, 0.0, 10.0).is_none());
    }
}
