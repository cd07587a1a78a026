//! A validated scene: triangles with per-vertex attributes, materials, decals and a light,
//! plus the BVH over the triangles (built for the scene, or a caller's tree refit to it).

use std::borrow::Cow;

use super::bvh::{mesh_triangles, Tri, TriangleBvh};
use super::intersect::TriHit;
use super::procedural::{normalize, Decal, DecalGrid, DECAL_FLOATS};
use crate::error::{check_finite, check_indices, check_len, Error, Result};

/// Floats per material row: specular, shininess, wrap, pore_strength, pore_size,
/// mottle_strength, mottle_size, textured.
pub const MATERIAL_FLOATS: usize = 8;

/// How a surface reflects light. Sizes are in scene units (metres for heads).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Weight of the normalised Blinn–Phong lobe.
    pub specular: f32,
    /// Blinn–Phong exponent (> 0).
    pub shininess: f32,
    /// Wrap lighting in [0, 1): diffuse light reaches `wrap` past the terminator (a cheap
    /// stand-in for subsurface scattering in skin).
    pub wrap: f32,
    /// Pore darkening in [0, 1] (pores also lose specular) and the pore cell size.
    pub pore_strength: f32,
    pub pore_size: f32,
    /// Low-frequency albedo variation in [0, 1] and its feature size.
    pub mottle_strength: f32,
    pub mottle_size: f32,
    /// Multiply the albedo by the texture at the hit's UV.
    pub textured: bool,
}

/// The key light (directional, with an angular radius for soft shadows) and a hemisphere
/// ambient term.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// Unit direction towards the light, world space.
    pub direction: [f32; 3],
    pub color: [f32; 3],
    /// Angular radius in radians (0: hard shadows).
    pub angular_radius: f32,
    pub ambient_up: [f32; 3],
    pub ambient_down: [f32; 3],
    /// Unit world "up" of the ambient hemisphere.
    pub up: [f32; 3],
}

/// An RGB texture, row 0 at v = 1 (OBJ `vt` convention), sampled bilinearly with clamped
/// coordinates.
#[derive(Debug, Clone, Copy)]
pub struct Texture<'a> {
    pub data: &'a [f32],
    pub width: usize,
    pub height: usize,
}

impl Texture<'_> {
    pub fn sample(&self, uv: [f32; 2]) -> [f32; 3] {
        // NaN UVs become 0 through the clamp's `max`; the result stays finite.
        let x = (uv[0].clamp(0.0, 1.0) * self.width as f32 - 0.5).max(0.0);
        let y = ((1.0 - uv[1].clamp(0.0, 1.0)) * self.height as f32 - 0.5).max(0.0);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x0, y0) = (x0.min(self.width - 1), y0.min(self.height - 1));
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let texel = |x: usize, y: usize, c: usize| self.data[(y * self.width + x) * 3 + c];
        [0, 1, 2].map(|c| {
            let top = texel(x0, y0, c) * (1.0 - fx) + texel(x1, y0, c) * fx;
            let bottom = texel(x0, y1, c) * (1.0 - fx) + texel(x1, y1, c) * fx;
            top * (1.0 - fy) + bottom * fy
        })
    }
}

/// Borrowed scene arrays (flat, row-major), as they cross from Python.
#[derive(Debug, Clone, Copy)]
pub struct SceneInputs<'a> {
    /// (V, 3) world positions.
    pub vertices: &'a [f32],
    /// (F, 3) vertex indices.
    pub faces: &'a [i32],
    /// (V, 3) shading normals (need not be unit; zero falls back to the face normal).
    pub normals: &'a [f32],
    /// (V, 3) albedo in [0, 1].
    pub colors: &'a [f32],
    /// (V, 3) solid-texture coordinates (the rest pose) for the procedural detail.
    pub solid: &'a [f32],
    /// (V, 2) texture coordinates, needed when a material is textured.
    pub uvs: Option<&'a [f32]>,
    /// (F,) index into `materials`.
    pub face_material: &'a [i32],
    /// (M, MATERIAL_FLOATS)
    pub materials: &'a [f32],
    /// (D, DECAL_FLOATS)
    pub decals: &'a [f32],
    pub texture: Option<Texture<'a>>,
    pub light: Light,
}

/// A scene ready to trace.
pub struct Scene<'a> {
    pub inputs: SceneInputs<'a>,
    pub materials: Vec<Material>,
    pub decals: DecalGrid,
    bvh: Cow<'a, TriangleBvh>,
}

impl<'a> Scene<'a> {
    /// Validates every array (shapes, finiteness, index ranges, material values) and builds
    /// the BVH. Errors name the argument.
    pub fn new(inputs: SceneInputs<'a>) -> Result<Self> {
        let (materials, decals, tris) = validate(&inputs)?;
        // Single-threaded build: the same tree for the same triangles, which keeps
        // tie-breaking between equal hits deterministic.
        let bvh = Cow::Owned(TriangleBvh::build(&tris));
        Ok(Self {
            inputs,
            materials,
            decals: DecalGrid::new(decals),
            bvh,
        })
    }

    /// Like [`Scene::new`], but refits `bvh` (built over as many triangles) to the scene
    /// instead of building one: far cheaper for a mesh whose topology never changes. The
    /// tree then depends only on what `bvh` was built from, never on earlier refits.
    pub fn with_bvh(inputs: SceneInputs<'a>, bvh: &'a mut TriangleBvh) -> Result<Self> {
        let (materials, decals, tris) = validate(&inputs)?;
        bvh.refit(&tris)?;
        Ok(Self {
            inputs,
            materials,
            decals: DecalGrid::new(decals),
            bvh: Cow::Borrowed(bvh),
        })
    }

    pub fn num_faces(&self) -> usize {
        self.inputs.faces.len() / 3
    }

    /// The closest hit along `origin + t·dir` (unit `dir`) with `t` in `(t_min, t_max)`:
    /// (face, hit). Ties keep the first face the traversal meets (a fixed order).
    #[inline]
    pub fn closest_hit(
        &self,
        origin: [f32; 3],
        dir: [f32; 3],
        t_min: f32,
        t_max: f32,
    ) -> Option<(usize, TriHit)> {
        self.bvh.closest_hit(origin, dir, t_min, t_max)
    }

    /// Whether anything lies along `origin + t·dir` for `t` in `(t_min, t_max)`.
    #[inline]
    pub fn occluded(&self, origin: [f32; 3], dir: [f32; 3], t_min: f32, t_max: f32) -> bool {
        self.bvh.occluded(origin, dir, t_min, t_max)
    }

    /// The corners of `face`.
    pub fn triangle(&self, face: usize) -> Tri {
        let v = self.inputs.vertices;
        let f = &self.inputs.faces[face * 3..face * 3 + 3];
        [0, 1, 2].map(|k| {
            let i = f[k] as usize * 3;
            [v[i], v[i + 1], v[i + 2]]
        })
    }

    /// Barycentric interpolation of a per-vertex attribute with `D` floats per vertex.
    #[inline]
    pub fn interpolate<const D: usize>(&self, attr: &[f32], face: usize, hit: &TriHit) -> [f32; D] {
        let f = &self.inputs.faces[face * 3..face * 3 + 3];
        let w = [1.0 - hit.u - hit.v, hit.u, hit.v];
        let mut out = [0.0; D];
        for (corner, &vi) in f.iter().enumerate() {
            let base = vi as usize * D;
            for d in 0..D {
                out[d] += w[corner] * attr[base + d];
            }
        }
        out
    }
}

/// Checks every array of `inputs`; returns the parsed materials and decals and the
/// triangles' corner positions.
fn validate(inputs: &SceneInputs) -> Result<(Vec<Material>, Vec<Decal>, Vec<Tri>)> {
    let tris = mesh_triangles(inputs.vertices, inputs.faces)?;
    let (nv, nf) = (inputs.vertices.len() / 3, inputs.faces.len() / 3);
    check_len("normals", inputs.normals, nv * 3, "(V, 3) like vertices")?;
    check_len("colors", inputs.colors, nv * 3, "(V, 3) like vertices")?;
    check_len("solid", inputs.solid, nv * 3, "(V, 3) like vertices")?;
    check_len("face_material", inputs.face_material, nf, "(F,) like faces")?;
    check_finite("normals", inputs.normals)?;
    check_finite("colors", inputs.colors)?;
    check_finite("solid", inputs.solid)?;
    let nm = inputs.materials.len() / MATERIAL_FLOATS;
    check_len(
        "materials",
        inputs.materials,
        nm * MATERIAL_FLOATS,
        "(M, 8): specular, shininess, wrap, pore_strength, pore_size, mottle_strength, mottle_size, textured",
    )?;
    check_finite("materials", inputs.materials)?;
    check_indices("face_material", inputs.face_material, 0, nm as i64)?;
    let materials = parse_materials(inputs.materials)?;
    if materials.iter().any(|m| m.textured) {
        let uvs = inputs.uvs.ok_or_else(|| Error::Invalid {
            arg: "uvs",
            reason: "a textured material needs uvs and a texture".into(),
        })?;
        check_len("uvs", uvs, nv * 2, "(V, 2) like vertices")?;
        check_finite("uvs", uvs)?;
        let tex = inputs.texture.ok_or_else(|| Error::Invalid {
            arg: "texture",
            reason: "a textured material needs a texture".into(),
        })?;
        if tex.width == 0 || tex.height == 0 {
            return Err(Error::Invalid {
                arg: "texture",
                reason: "must be at least 1×1".into(),
            });
        }
        check_len("texture", tex.data, tex.width * tex.height * 3, "(TH, TW, 3)")?;
        check_finite("texture", tex.data)?;
    }
    let decals = parse_decals(inputs.decals)?;
    check_light(&inputs.light)?;

    Ok((materials, decals, tris))
}

fn parse_materials(table: &[f32]) -> Result<Vec<Material>> {
    table
        .chunks_exact(MATERIAL_FLOATS)
        .enumerate()
        .map(|(i, m)| {
            let material = Material {
                specular: m[0],
                shininess: m[1],
                wrap: m[2],
                pore_strength: m[3],
                pore_size: m[4],
                mottle_strength: m[5],
                mottle_size: m[6],
                textured: m[7] != 0.0,
            };
            let ok = m[0] >= 0.0
                && m[1] > 0.0
                && (0.0..1.0).contains(&m[2])
                && (0.0..=1.0).contains(&m[3])
                && (m[3] == 0.0 || m[4] > 0.0)
                && (0.0..=1.0).contains(&m[5])
                && (m[5] == 0.0 || m[6] > 0.0);
            if ok {
                Ok(material)
            } else {
                Err(Error::Invalid {
                    arg: "materials",
                    reason: format!(
                        "row {i} {m:?} needs specular ≥ 0, shininess > 0, wrap in [0, 1), \
                         strengths in [0, 1] and positive sizes where a strength is set"
                    ),
                })
            }
        })
        .collect()
}

fn parse_decals(table: &[f32]) -> Result<Vec<Decal>> {
    let n = table.len() / DECAL_FLOATS;
    check_len(
        "decals",
        table,
        n * DECAL_FLOATS,
        "(D, 12): a(3), b(3), radius, rgb(3), opacity, pattern",
    )?;
    check_finite("decals", table)?;
    table
        .chunks_exact(DECAL_FLOATS)
        .enumerate()
        .map(|(i, d)| {
            let pattern = d[11];
            if !(d[6] > 0.0 && (0.0..=1.0).contains(&d[10]) && (pattern == 0.0 || pattern == 1.0)) {
                return Err(Error::Invalid {
                    arg: "decals",
                    reason: format!("row {i} needs radius > 0, opacity in [0, 1], pattern 0 or 1"),
                });
            }
            Ok(Decal {
                a: [d[0], d[1], d[2]],
                b: [d[3], d[4], d[5]],
                radius: d[6],
                color: [d[7], d[8], d[9]],
                opacity: d[10],
                pattern: pattern as u32,
            })
        })
        .collect()
}

fn check_light(light: &Light) -> Result<()> {
    let values = [
        &light.direction[..],
        &light.color[..],
        &light.ambient_up[..],
        &light.ambient_down[..],
        &light.up[..],
        &[light.angular_radius][..],
    ]
    .concat();
    check_finite("light", &values)?;
    let unit = |v: [f32; 3]| {
        (normalize(v)[0] - v[0]).abs() + (normalize(v)[1] - v[1]).abs() + (normalize(v)[2] - v[2]).abs()
            < 1e-4
    };
    if !(unit(light.direction) && unit(light.up) && light.direction != [0.0; 3] && light.up != [0.0; 3]) {
        return Err(Error::Invalid {
            arg: "light",
            reason: "direction and up must be unit vectors".into(),
        });
    }
    if !(0.0..1.0).contains(&light.angular_radius) {
        return Err(Error::Invalid {
            arg: "light",
            reason: format!(
                "angular_radius must be in [0, 1) rad, got {}",
                light.angular_radius
            ),
        });
    }
    Ok(())
}
