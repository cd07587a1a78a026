//! Rendering: stratified supersampling per pixel, shading with a soft-shadowed key light,
//! hemisphere ambient and a Blinn–Phong lobe, tiles in parallel with rayon. Every sample's
//! jitter is a hash of (pixel, sample, seed), so the image does not depend on the thread
//! count or the tile schedule.

use rayon::prelude::*;

use super::intersect::{cross, dot, sub, TriHit};
use super::procedural::{hash, normalize, pores, unit, value_noise};
use super::scene::Scene;
use crate::camera::Camera;
use crate::error::{checked_size, Error, Result};

/// Side of the square pixel tiles handed to rayon.
const TILE: usize = 16;

/// Most samples per pixel side accepted (16 × 16 = 256 spp).
pub const MAX_SAMPLES_PER_SIDE: u32 = 16;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderSettings {
    /// Samples per pixel side: `n × n` stratified samples (1: one ray through the centre).
    pub samples_per_side: u32,
    /// Samples per side where the first `n × n` disagree (coverage, material, or a depth
    /// spread above 1 %: silhouettes, hair, occlusion edges); the pixel is then rendered
    /// again with `m × m` samples. `m ≤ n` turns this off.
    pub edge_samples_per_side: u32,
    /// Trace shadow rays towards the key light.
    pub shadows: bool,
    /// Also trace the exact ray through each pixel centre for the `centre_*` outputs
    /// (one more ray per pixel); off, those outputs are empty.
    pub centre_hits: bool,
    /// Colour behind the scene (the RGB output is composited over it).
    pub background: [f32; 3],
    /// Seed of the sample jitter and light sampling.
    pub seed: u32,
}

/// Per-pixel outputs, row-major `(H, W, C)`.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOutput {
    /// (H, W, 3) colour, the samples' mean, composited over the background.
    pub rgb: Vec<f32>,
    /// (H, W) fraction of samples that hit the scene.
    pub alpha: Vec<f32>,
    /// (H, W, 3) unit shading normal in OpenCV camera axes (x right, y down, z forward;
    /// facing the camera means z < 0): the normalised mean over the samples that hit,
    /// zero where none did.
    pub normal: Vec<f32>,
    /// (H, W) linear view-space depth (camera z), mean over the samples that hit; 0 where
    /// none did.
    pub depth: Vec<f32>,
    /// (H, W) face hit by the ray through the pixel centre, −1 for none. This and the
    /// next two are empty unless `centre_hits` was set.
    pub centre_face: Vec<i32>,
    /// (H, W, 2) barycentrics (u, v) of vertices 1 and 2 of that face (0 for none).
    pub centre_bary: Vec<f32>,
    /// (H, W) distance along the unit centre ray to that hit (0 for none).
    pub centre_t: Vec<f32>,
}

/// One primary ray of a pixel (from the eye) and what it hit.
struct Traced {
    /// Sample index within the pixel's `n × n` pattern.
    k: u32,
    dir: [f32; 3],
    /// (face, hit, hit point, camera depth).
    hit: Option<(usize, TriHit, [f32; 3], f32)>,
}

struct Rig<'a> {
    scene: &'a Scene<'a>,
    camera: &'a Camera,
    settings: RenderSettings,
    /// Rows of the world→camera rotation (camera axes in world space).
    rot: [[f32; 3]; 3],
    eye: [f32; 3],
}

/// Renders `scene` through `camera`.
pub fn render(scene: &Scene, camera: &Camera, settings: RenderSettings) -> Result<RenderOutput> {
    if !(1..=MAX_SAMPLES_PER_SIDE).contains(&settings.samples_per_side) {
        return Err(Error::Invalid {
            arg: "samples_per_side",
            reason: format!(
                "must be in [1, {MAX_SAMPLES_PER_SIDE}], got {}",
                settings.samples_per_side
            ),
        });
    }
    if settings.edge_samples_per_side > MAX_SAMPLES_PER_SIDE {
        return Err(Error::Invalid {
            arg: "edge_samples_per_side",
            reason: format!(
                "must be at most {MAX_SAMPLES_PER_SIDE}, got {}",
                settings.edge_samples_per_side
            ),
        });
    }
    if !settings.background.iter().all(|c| c.is_finite()) {
        return Err(Error::Invalid {
            arg: "background",
            reason: format!("must be finite, got {:?}", settings.background),
        });
    }
    let (w, h) = (camera.width as usize, camera.height as usize);
    let pixels = checked_size("image pixels", &[w, h, 3], 1 << 32)? / 3;
    let m = &camera.viewmat;
    let rot = [0, 1, 2].map(|r| [m[r][0], m[r][1], m[r][2]]);
    let t = [m[0][3], m[1][3], m[2][3]];
    // Camera centre −Rᵀt; the viewmat is assumed rigid (the Camera type's contract).
    let eye = [0, 1, 2].map(|c| -(rot[0][c] * t[0] + rot[1][c] * t[1] + rot[2][c] * t[2]));
    let rig = Rig {
        scene,
        camera,
        settings,
        rot,
        eye,
    };

    let tiles_x = w.div_ceil(TILE);
    let tiles: Vec<TileOut> = (0..tiles_x * h.div_ceil(TILE))
        .into_par_iter()
        .map(|i| rig.tile((i % tiles_x) * TILE, (i / tiles_x) * TILE))
        .collect();

    let mut out = RenderOutput {
        rgb: vec![0.0; pixels * 3],
        alpha: vec![0.0; pixels],
        normal: vec![0.0; pixels * 3],
        depth: vec![0.0; pixels],
        centre_face: Vec::new(),
        centre_bary: Vec::new(),
        centre_t: Vec::new(),
    };
    if settings.centre_hits {
        out.centre_face = vec![-1; pixels];
        out.centre_bary = vec![0.0; pixels * 2];
        out.centre_t = vec![0.0; pixels];
    }
    for tile in tiles {
        for (k, &(x, y)) in tile.coords.iter().enumerate() {
            let p = y * w + x;
            out.rgb[p * 3..p * 3 + 3].copy_from_slice(&tile.rgb[k]);
            out.normal[p * 3..p * 3 + 3].copy_from_slice(&tile.normal[k]);
            out.alpha[p] = tile.alpha[k];
            out.depth[p] = tile.depth[k];
            if settings.centre_hits {
                out.centre_face[p] = tile.centre_face[k];
                out.centre_bary[p * 2..p * 2 + 2].copy_from_slice(&tile.centre_bary[k]);
                out.centre_t[p] = tile.centre_t[k];
            }
        }
    }
    Ok(out)
}

/// A pixel's accumulated samples.
struct PixelAcc {
    color: [f32; 3],
    normal: [f32; 3],
    hits: usize,
    depth: f32,
    count: usize,
}

/// All rays missed, or all hit one material within a 1 % depth spread.
fn uniform(rays: &[Traced], face_material: &[i32]) -> bool {
    let mut materials = (i32::MAX, i32::MIN);
    let mut depths = (f32::INFINITY, 0.0f32);
    let mut hits = 0;
    for (face, _, _, z) in rays.iter().filter_map(|r| r.hit) {
        let m = face_material[face];
        materials = (materials.0.min(m), materials.1.max(m));
        depths = (depths.0.min(z), depths.1.max(z));
        hits += 1;
    }
    hits == 0 || (hits == rays.len() && materials.0 == materials.1 && depths.1 - depths.0 <= 0.01 * depths.0)
}

#[derive(Default)]
struct TileOut {
    coords: Vec<(usize, usize)>,
    rgb: Vec<[f32; 3]>,
    normal: Vec<[f32; 3]>,
    alpha: Vec<f32>,
    depth: Vec<f32>,
    centre_face: Vec<i32>,
    centre_bary: Vec<[f32; 2]>,
    centre_t: Vec<f32>,
}

impl Rig<'_> {
    fn tile(&self, x0: usize, y0: usize) -> TileOut {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let mut out = TileOut::default();
        let mut rays = Vec::new();
        for y in y0..(y0 + TILE).min(h) {
            for x in x0..(x0 + TILE).min(w) {
                self.pixel(x, y, &mut rays, &mut out);
            }
        }
        out
    }

    /// Traces the pixel's `n × n` rays; where they disagree (and the edge pattern is
    /// larger), traces the `m × m` edge pattern instead. Only the rays kept are shaded.
    fn pixel(&self, x: usize, y: usize, rays: &mut Vec<Traced>, out: &mut TileOut) {
        let pixel_id =
            (y as u32).wrapping_mul(0x9e37_79b9) ^ (x as u32) ^ self.settings.seed.wrapping_mul(0x85eb_ca6b);
        let mut side = self.settings.samples_per_side;
        self.trace_pixel(x, y, pixel_id, side, rays);
        let edge = self.settings.edge_samples_per_side;
        if edge > side && !uniform(rays, self.scene.inputs.face_material) {
            side = edge;
            self.trace_pixel(x, y, pixel_id, side, rays);
        }
        let acc = self.shade_pixel(rays, pixel_id, side);
        let PixelAcc {
            color,
            normal,
            hits,
            depth,
            count,
            ..
        } = acc;
        let count = count as f32;
        out.coords.push((x, y));
        out.rgb.push(color.map(|c| c / count));
        out.alpha.push(hits as f32 / count);
        out.depth.push(if hits > 0 { depth / hits as f32 } else { 0.0 });
        let cam_normal = normalize(self.to_camera_dir(normal));
        out.normal.push(if hits > 0 { cam_normal } else { [0.0; 3] });
        if !self.settings.centre_hits {
            return;
        }
        // The exact centre ray, for the geometric outputs.
        let (origin, dir, t_min, t_max) = self.primary_ray(x as f32 + 0.5, y as f32 + 0.5);
        match self.scene.closest_hit(origin, dir, t_min, t_max) {
            Some((face, hit)) => {
                out.centre_face.push(face as i32);
                out.centre_bary.push([hit.u, hit.v]);
                out.centre_t.push(hit.t);
            }
            None => {
                out.centre_face.push(-1);
                out.centre_bary.push([0.0; 2]);
                out.centre_t.push(0.0);
            }
        }
    }

    /// The `n × n` stratified primary rays of pixel (x, y) and their closest hits, into
    /// `rays` (cleared first).
    fn trace_pixel(&self, x: usize, y: usize, pixel_id: u32, n: u32, rays: &mut Vec<Traced>) {
        rays.clear();
        for j in 0..n {
            for i in 0..n {
                let k = j * n + i;
                let (ox, oy) = if n == 1 {
                    (0.5, 0.5)
                } else {
                    let h = hash(pixel_id ^ hash(k.wrapping_add(0x632b_e5ab)));
                    (
                        (i as f32 + unit(h)) / n as f32,
                        (j as f32 + unit(hash(h))) / n as f32,
                    )
                };
                let (origin, dir, t_min, t_max) = self.primary_ray(x as f32 + ox, y as f32 + oy);
                let hit = self
                    .scene
                    .closest_hit(origin, dir, t_min, t_max)
                    .map(|(face, hit)| {
                        let p = [0, 1, 2].map(|c| origin[c] + hit.t * dir[c]);
                        (face, hit, p, dot(self.rot[2], sub(p, self.eye)))
                    });
                rays.push(Traced { k, dir, hit });
            }
        }
    }

    /// Shades the traced rays of a pixel (`side × side` of them) and accumulates them.
    fn shade_pixel(&self, rays: &[Traced], pixel_id: u32, side: u32) -> PixelAcc {
        let mut acc = PixelAcc {
            color: [0.0; 3],
            normal: [0.0; 3],
            hits: 0,
            depth: 0.0,
            count: rays.len(),
        };
        for ray in rays {
            let Some((face, hit, p, z)) = ray.hit else {
                for c in 0..3 {
                    acc.color[c] += self.settings.background[c];
                }
                continue;
            };
            let (color, nrm) = self.shade(ray.dir, face, &hit, p, pixel_id, ray.k, side);
            for c in 0..3 {
                acc.color[c] += color[c];
            }
            acc.hits += 1;
            acc.depth += z;
            for c in 0..3 {
                acc.normal[c] += nrm[c];
            }
        }
        acc
    }

    fn to_camera_dir(&self, v: [f32; 3]) -> [f32; 3] {
        self.rot.map(|r| dot(r, v))
    }

    /// The unit world-space ray through pixel coordinates (px, py), with the `t` range
    /// that keeps camera depth within [near, far].
    fn primary_ray(&self, px: f32, py: f32) -> ([f32; 3], [f32; 3], f32, f32) {
        let c = self.camera;
        let d_cam = [(px - c.cx) / c.fx, (py - c.cy) / c.fy, 1.0];
        let len = dot(d_cam, d_cam).sqrt();
        let d_world = [0, 1, 2].map(|k| {
            (self.rot[0][k] * d_cam[0] + self.rot[1][k] * d_cam[1] + self.rot[2][k] * d_cam[2]) / len
        });
        (self.eye, normalize(d_world), c.near * len, c.far * len)
    }

    /// (colour, world shading normal) of a primary ray along `dir` hitting `face` at `p`.
    fn shade(
        &self,
        dir: [f32; 3],
        face: usize,
        hit: &TriHit,
        p: [f32; 3],
        pixel_id: u32,
        k: u32,
        side: u32,
    ) -> ([f32; 3], [f32; 3]) {
        let scene = self.scene;
        let inputs = &scene.inputs;
        let tri = &scene.triangle(face);
        let mut geo = normalize(cross(sub(tri[1], tri[0]), sub(tri[2], tri[0])));
        if dot(geo, dir) > 0.0 {
            geo = geo.map(|x| -x);
        }
        let mut n: [f32; 3] = scene.interpolate::<3>(inputs.normals, face, hit);
        n = normalize(n);
        if dot(n, n) < 0.5 {
            n = geo;
        }
        if dot(n, dir) > 0.0 {
            n = n.map(|x| -x); // seen from behind (thin ribbons, open meshes)
        }
        let material = scene.materials[inputs.face_material[face] as usize];

        let mut albedo: [f32; 3] = scene.interpolate::<3>(inputs.colors, face, hit);
        if material.textured {
            if let (Some(uvs), Some(tex)) = (inputs.uvs, inputs.texture) {
                let uv: [f32; 2] = scene.interpolate::<2>(uvs, face, hit);
                let t = tex.sample(uv);
                albedo = [0, 1, 2].map(|c| albedo[c] * t[c]);
            }
        }
        let solid: [f32; 3] = scene.interpolate::<3>(inputs.solid, face, hit);
        let mut shine = 1.0;
        if material.mottle_strength > 0.0 {
            let q = solid.map(|x| x / material.mottle_size);
            let m = 0.65 * value_noise(q, 11) + 0.35 * value_noise(q.map(|x| x * 2.7), 12);
            let f = 1.0 + material.mottle_strength * (m - 0.5) * 2.0;
            albedo = albedo.map(|a| a * f);
        }
        if material.pore_strength > 0.0 {
            let d = pores(solid.map(|x| x / material.pore_size), 7) * material.pore_strength;
            albedo = albedo.map(|a| a * (1.0 - d));
            shine = 1.0 - d;
        }
        albedo = scene.decals.apply(solid, albedo).map(|a| a.clamp(0.0, 1.0));

        let light = &inputs.light;
        let l = self.light_direction(pixel_id, k, side);
        let ndl = dot(n, l);
        let lit = (ndl + material.wrap) / (1.0 + material.wrap);
        let mut visible = if lit > 0.0 { 1.0 } else { 0.0 };
        // Only surfaces facing the light cast shadow rays: past the terminator the wrapped
        // diffuse term stands for light scattered under the skin, which a ray from the
        // surface towards the light would always find blocked by the surface itself.
        if visible > 0.0 && self.settings.shadows && dot(geo, l) > 0.0 {
            let eps = 1e-4 * (1.0 + hit.t);
            let start = [0, 1, 2].map(|c| p[c] + geo[c] * eps);
            if scene.occluded(start, l, 0.0, f32::INFINITY) {
                visible = 0.0;
            }
        }
        let diffuse = lit.max(0.0) * visible;
        let view = dir.map(|x| -x);
        let half = normalize([0, 1, 2].map(|c| l[c] + view[c]));
        let spec_lobe = if ndl > 0.0 {
            let nh = dot(n, half).max(0.0);
            (material.shininess + 8.0) / (8.0 * std::f32::consts::PI) * nh.powf(material.shininess)
        } else {
            0.0
        };
        let specular = material.specular * shine * spec_lobe * ndl.max(0.0) * visible;
        let sky = 0.5 + 0.5 * dot(n, light.up);
        let color = [0, 1, 2].map(|c| {
            let ambient = light.ambient_down[c] + (light.ambient_up[c] - light.ambient_down[c]) * sky;
            albedo[c] * (light.color[c] * diffuse + ambient) + light.color[c] * specular
        });
        (color, n)
    }

    /// A direction in the light's cone (uniform over the cone's cap), stratified by the
    /// sample index so that a pixel's samples cover the light.
    fn light_direction(&self, pixel_id: u32, k: u32, n: u32) -> [f32; 3] {
        let light = &self.scene.inputs.light;
        if light.angular_radius == 0.0 {
            return light.direction;
        }
        let count = n * n;
        // Decorrelate light strata from pixel strata with a per-pixel rotation of indices.
        let stratum = (k + hash(pixel_id ^ 0x27d4_eb2f) % count) % count;
        let h = hash(pixel_id ^ hash(k ^ 0x1656_67b1));
        let (si, sj) = (stratum % n, stratum / n);
        let u1 = (si as f32 + unit(h)) / n as f32;
        let u2 = (sj as f32 + unit(hash(h))) / n as f32;
        let cos_max = light.angular_radius.cos();
        let cos_t = 1.0 - u1 * (1.0 - cos_max);
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        let phi = 2.0 * std::f32::consts::PI * u2;
        let a = light.direction;
        let helper = if a[1].abs() < 0.9 {
            [0.0, 1.0, 0.0]
        } else {
            [1.0, 0.0, 0.0]
        };
        let e1 = normalize(cross(helper, a));
        let e2 = cross(a, e1);
        normalize([0, 1, 2].map(|c| a[c] * cos_t + (e1[c] * phi.cos() + e2[c] * phi.sin()) * sin_t))
    }
}
