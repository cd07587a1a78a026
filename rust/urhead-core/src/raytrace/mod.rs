//! A CPU ray tracer for ground-truth images, independent of the training renderer (it
//! shares no code with the rasterizer): triangles in obvhs' compressed wide BVH, smooth
//! shading from per-vertex normals, albedo from per-vertex colour × an optional texture ×
//! procedural detail (pores, mottling, decals) evaluated at every hit, a soft-shadowed key
//! light with a Blinn–Phong lobe plus hemisphere ambient, stratified supersampling, and
//! per-pixel colour, coverage, camera-space normal and depth. No gradients.
//!
//! Deterministic: the BVH build is single-threaded, each sample's randomness is a hash of
//! its pixel and index, and tiles write disjoint pixels. For animation, a [`TriangleBvh`]
//! built once is refit to every frame ([`Scene::with_bvh`]) instead of rebuilt.

pub mod bvh;
pub mod intersect;
pub mod procedural;
pub mod render;
pub mod scene;

pub use bvh::TriangleBvh;
pub use intersect::{intersect_triangle, TriHit};
pub use procedural::{Decal, DECAL_FLOATS};
pub use render::{render, RenderOutput, RenderSettings, MAX_SAMPLES_PER_SIDE};
pub use scene::{Light, Material, Scene, SceneInputs, Texture, MATERIAL_FLOATS};
