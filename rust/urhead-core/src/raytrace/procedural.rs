//! Procedural albedo evaluated at every hit, in the surface's "solid" coordinates (its rest
//! pose, so patterns move with the skin): pores (cellular noise), mottling (value noise)
//! and decals (capsules of colour: freckles, a mole, eyebrow hairs, iris and pupil). It has
//! no resolution limit, so it holds detail finer than any UV map a model can learn.

/// Integer hash (a 32-bit avalanche mix), the source of all randomness: a pure function
/// of its inputs, so renders are deterministic.
#[inline]
pub fn hash(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

#[inline]
pub fn hash3(i: i32, j: i32, k: i32, seed: u32) -> u32 {
    hash(
        (i as u32)
            .wrapping_mul(0x8da6_b343)
            .wrapping_add((j as u32).wrapping_mul(0xd816_3841))
            .wrapping_add((k as u32).wrapping_mul(0xcb1a_b31f))
            .wrapping_add(hash(seed)),
    )
}

/// A uniform float in [0, 1) from a hash.
#[inline]
pub fn unit(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

#[inline]
fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Smoothstep from `e0` to `e1`.
#[inline]
pub fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    smooth(((x - e0) / (e1 - e0)).clamp(0.0, 1.0))
}

/// Trilinear value noise in [0, 1] with cells of size 1.
pub fn value_noise(p: [f32; 3], seed: u32) -> f32 {
    let cell = p.map(|x| x.floor());
    let f = [0, 1, 2].map(|a| smooth(p[a] - cell[a]));
    let c = cell.map(|x| x as i32);
    let corner = |dx, dy, dz| unit(hash3(c[0] + dx, c[1] + dy, c[2] + dz, seed));
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), f[0]);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), f[0]);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), f[0]);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), f[0]);
    lerp(lerp(x00, x10, f[1]), lerp(x01, x11, f[1]), f[2])
}

/// Largest pore radius (0.18 + 0.17) plus a margin: a pore of a neighbouring cell can
/// reach `p` only when `p` lies closer than this to the face the two cells share.
const PORE_REACH: f32 = 0.36;

/// Pore darkening in [0, 1] at `p` (cells of size 1): each cell holds a pore of random
/// position, radius and depth with probability ~0.7; 0 between pores.
pub fn pores(p: [f32; 3], seed: u32) -> f32 {
    let c = p.map(|x| x.floor() as i32);
    // Only the neighbours whose pores can reach `p`: ~5 cells instead of 27, same result.
    let reach = |a: usize| {
        let f = p[a] - c[a] as f32;
        (if f < PORE_REACH { -1 } else { 0 })..=(if f > 1.0 - PORE_REACH { 1 } else { 0 })
    };
    let mut depth = 0.0f32;
    for dz in reach(2) {
        for dy in reach(1) {
            for dx in reach(0) {
                depth = depth.max(pore_cell(p, [c[0] + dx, c[1] + dy, c[2] + dz], seed));
            }
        }
    }
    depth
}

/// The darkening at `p` from the pore of cell `(i, j, k)` (0 outside it or without one).
#[inline]
fn pore_cell(p: [f32; 3], [i, j, k]: [i32; 3], seed: u32) -> f32 {
    let h = hash3(i, j, k, seed);
    if unit(h) > 0.7 {
        return 0.0;
    }
    let centre = [
        i as f32 + unit(hash(h ^ 0x68e3_1da4)),
        j as f32 + unit(hash(h ^ 0xb529_7a4d)),
        k as f32 + unit(hash(h ^ 0x1b56_c4e9)),
    ];
    let radius = 0.18 + 0.17 * unit(hash(h ^ 0x7f4a_7c15));
    let d2 = (0..3).map(|a| (p[a] - centre[a]).powi(2)).sum::<f32>();
    if d2 < radius * radius {
        let s = 1.0 - smoothstep(0.3 * radius, radius, d2.sqrt());
        s * (0.5 + 0.5 * unit(hash(h ^ 0x2545_f491)))
    } else {
        0.0
    }
}

/// A capsule of colour in solid coordinates. `pattern` 0: flat colour; 1: an iris, whose
/// `a` is the iris centre on the eyeball surface and `b` the eyeball centre (its axis),
/// coloured with radial fibres and a dark limbal ring.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Decal {
    pub a: [f32; 3],
    pub b: [f32; 3],
    pub radius: f32,
    pub color: [f32; 3],
    pub opacity: f32,
    pub pattern: u32,
}

/// Number of floats per decal in the flat table: a(3) b(3) radius rgb(3) opacity pattern.
pub const DECAL_FLOATS: usize = 12;

impl Decal {
    fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let lo = [0, 1, 2].map(|k| self.a[k].min(self.b[k]) - self.radius);
        let hi = [0, 1, 2].map(|k| self.a[k].max(self.b[k]) + self.radius);
        (lo, hi)
    }

    /// (colour, coverage in [0, 1]) at `p`.
    fn eval(&self, p: [f32; 3]) -> ([f32; 3], f32) {
        let r = self.radius;
        if self.pattern == 1 {
            let d = [0, 1, 2].map(|k| p[k] - self.a[k]);
            let dist = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if dist >= r {
                return (self.color, 0.0);
            }
            // Angle around the eye axis from a frame built on it.
            let axis = normalize([0, 1, 2].map(|k| self.a[k] - self.b[k]));
            let helper = if axis[1].abs() < 0.9 {
                [0.0, 1.0, 0.0]
            } else {
                [1.0, 0.0, 0.0]
            };
            let e1 = normalize(cross3(helper, axis));
            let e2 = cross3(axis, e1);
            let x = d[0] * e1[0] + d[1] * e1[1] + d[2] * e1[2];
            let y = d[0] * e2[0] + d[1] * e2[1] + d[2] * e2[2];
            let angle = y.atan2(x);
            let fibres = value_noise([angle * 9.0, dist / r * 3.0, 0.5], 0x5bd1_e995);
            let ring = smoothstep(0.75 * r, r, dist);
            let shade = (0.65 + 0.7 * fibres) * (1.0 - 0.6 * ring);
            let coverage = self.opacity * (1.0 - smoothstep(0.92 * r, r, dist));
            (self.color.map(|c| (c * shade).min(1.0)), coverage)
        } else {
            let ab = [0, 1, 2].map(|k| self.b[k] - self.a[k]);
            let ap = [0, 1, 2].map(|k| p[k] - self.a[k]);
            let len2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2];
            let s = if len2 > 0.0 {
                ((ap[0] * ab[0] + ap[1] * ab[1] + ap[2] * ab[2]) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let d2 = (0..3).map(|k| (ap[k] - s * ab[k]).powi(2)).sum::<f32>();
            if d2 >= r * r {
                return (self.color, 0.0);
            }
            (
                self.color,
                self.opacity * (1.0 - smoothstep(0.5 * r, r, d2.sqrt())),
            )
        }
    }
}

fn cross3(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    super::intersect::cross(a, b)
}

pub fn normalize(v: [f32; 3]) -> [f32; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if n > 0.0 {
        v.map(|x| x / n)
    } else {
        v
    }
}

/// Decals binned into a uniform grid over their bounds, so a lookup visits only the few
/// decals near a point. Cells list decals in table order, so blending is deterministic.
#[derive(Debug, Clone)]
pub struct DecalGrid {
    decals: Vec<Decal>,
    lo: [f32; 3],
    inv_cell: [f32; 3],
    dims: [usize; 3],
    cell_start: Vec<u32>,
    items: Vec<u32>,
}

impl DecalGrid {
    pub fn new(decals: Vec<Decal>) -> Self {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for d in &decals {
            let (a, b) = d.bounds();
            for k in 0..3 {
                lo[k] = lo[k].min(a[k]);
                hi[k] = hi[k].max(b[k]);
            }
        }
        let side = ((decals.len() as f32).cbrt() * 2.0).clamp(1.0, 64.0) as usize;
        let dims = [side; 3];
        let extent = [0, 1, 2].map(|k| (hi[k] - lo[k]).max(1e-9));
        let inv_cell = [0, 1, 2].map(|k| dims[k] as f32 / extent[k]);
        let mut grid = Self {
            decals,
            lo,
            inv_cell,
            dims,
            cell_start: vec![0; side * side * side + 1],
            items: Vec::new(),
        };
        if grid.decals.is_empty() {
            return grid;
        }
        let mut per_cell: Vec<Vec<u32>> = vec![Vec::new(); side * side * side];
        for (i, d) in grid.decals.iter().enumerate() {
            let (a, b) = d.bounds();
            let (c0, c1) = (grid.cell_of(a), grid.cell_of(b));
            for z in c0[2]..=c1[2] {
                for y in c0[1]..=c1[1] {
                    for x in c0[0]..=c1[0] {
                        per_cell[(z * side + y) * side + x].push(i as u32);
                    }
                }
            }
        }
        for (c, list) in per_cell.iter().enumerate() {
            grid.cell_start[c + 1] = grid.cell_start[c] + list.len() as u32;
            grid.items.extend_from_slice(list);
        }
        grid
    }

    fn cell_of(&self, p: [f32; 3]) -> [usize; 3] {
        [0, 1, 2].map(|k| {
            let c = ((p[k] - self.lo[k]) * self.inv_cell[k]).floor();
            // NaN → 0 via the `>=` test failing; clamp keeps boundary points inside.
            if c >= 0.0 {
                (c as usize).min(self.dims[k] - 1)
            } else {
                0
            }
        })
    }

    /// `albedo` with every decal covering `p` blended over it, in table order.
    pub fn apply(&self, p: [f32; 3], mut albedo: [f32; 3]) -> [f32; 3] {
        if self.decals.is_empty() {
            return albedo;
        }
        for k in 0..3 {
            let rel = (p[k] - self.lo[k]) * self.inv_cell[k];
            if !(rel >= 0.0 && rel < self.dims[k] as f32) {
                return albedo;
            }
        }
        let c = self.cell_of(p);
        let cell = (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0];
        let (start, end) = (self.cell_start[cell] as usize, self.cell_start[cell + 1] as usize);
        for &i in &self.items[start..end] {
            let (color, cover) = self.decals[i as usize].eval(p);
            if cover > 0.0 {
                albedo = [0, 1, 2].map(|k| albedo[k] + (color[k] - albedo[k]) * cover);
            }
        }
        albedo
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_bounded_and_deterministic() {
        for i in 0..500 {
            let p = [i as f32 * 0.37, i as f32 * -0.11, (i % 7) as f32 * 0.5];
            let n = value_noise(p, 3);
            assert!((0.0..=1.0).contains(&n));
            assert_eq!(n, value_noise(p, 3));
            let q = pores(p, 9);
            assert!((0.0..=1.0).contains(&q));
        }
    }

    #[test]
    fn pores_match_a_search_of_all_27_cells() {
        let mut rng = crate::testing::Rng::new(4);
        let mut dark = 0;
        for _ in 0..20_000 {
            // Large coordinates too (solid positions over a ~1e-3 pore size reach ~500).
            let p = [0, 1, 2].map(|_| rng.uniform(-600.0, 600.0) as f32);
            let c = p.map(|x| x.floor() as i32);
            let mut all = 0.0f32;
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        all = all.max(pore_cell(p, [c[0] + dx, c[1] + dy, c[2] + dz], 7));
                    }
                }
            }
            assert_eq!(pores(p, 7).to_bits(), all.to_bits(), "at {p:?}");
            dark += usize::from(all > 0.0);
        }
        assert!(dark > 500, "only {dark} points in a pore");
    }

    #[test]
    fn decal_grid_blends_capsules_in_order() {
        let red = Decal {
            a: [0.0; 3],
            b: [1.0, 0.0, 0.0],
            radius: 0.1,
            color: [1.0, 0.0, 0.0],
            opacity: 1.0,
            pattern: 0,
        };
        let blue = Decal {
            a: [1.0, 0.0, 0.0],
            b: [1.0, 0.0, 0.0],
            radius: 0.2,
            color: [0.0, 0.0, 1.0],
            opacity: 0.5,
            pattern: 0,
        };
        let grid = DecalGrid::new(vec![red, blue]);
        let grey = [0.5; 3];
        assert_eq!(grid.apply([0.5, 0.0, 0.0], grey), [1.0, 0.0, 0.0]);
        assert_eq!(grid.apply([0.5, 0.5, 0.0], grey), grey);
        // Red first, then half of blue over it.
        assert_eq!(grid.apply([1.0, 0.0, 0.0], grey), [0.5, 0.0, 0.5]);
        assert_eq!(grid.apply([f32::NAN, 0.0, 0.0], grey), grey);
    }
}
