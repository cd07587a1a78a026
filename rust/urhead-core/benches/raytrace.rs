//! Ray tracer: a ~100k-triangle lit, shadowed, pore-textured sphere filling about half of
//! a 512² image, at 1 and 16 samples per pixel (2 threads by default: RAYON_NUM_THREADS);
//! building its BVH, and refitting a kept one to moved vertices (an animation frame).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use urhead_core::raytrace::{render, Light, RenderSettings, Scene, SceneInputs, TriangleBvh};
use urhead_core::Camera;

/// A UV sphere of radius `r` at the origin with `stacks × slices × 2` triangles:
/// (vertices, faces, normals).
fn uv_sphere(r: f32, stacks: usize, slices: usize) -> (Vec<f32>, Vec<i32>, Vec<f32>) {
    let (mut v, mut n, mut f) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..=stacks {
        let theta = std::f32::consts::PI * i as f32 / stacks as f32;
        for j in 0..=slices {
            let phi = 2.0 * std::f32::consts::PI * j as f32 / slices as f32;
            let d = [theta.sin() * phi.cos(), theta.cos(), theta.sin() * phi.sin()];
            v.extend(d.map(|x| x * r));
            n.extend(d);
        }
    }
    let row = slices as i32 + 1;
    for i in 0..stacks as i32 {
        for j in 0..slices as i32 {
            let a = i * row + j;
            f.extend([a, a + row, a + 1, a + 1, a + row, a + row + 1]);
        }
    }
    (v, f, n)
}

fn bench_raytrace(c: &mut Criterion) {
    let (vertices, faces, normals) = uv_sphere(0.1, 224, 224);
    let nv = vertices.len() / 3;
    let colors = vec![0.7f32; nv * 3];
    let face_material = vec![0i32; faces.len() / 3];
    // specular, shininess, wrap, pores (strength, size), mottle (strength, size), textured
    let materials = [0.3f32, 40.0, 0.2, 0.5, 8e-4, 0.2, 0.02, 0.0];
    let s = 0.5f32.sqrt();
    let inputs = SceneInputs {
        vertices: &vertices,
        faces: &faces,
        normals: &normals,
        colors: &colors,
        solid: &vertices,
        uvs: None,
        face_material: &face_material,
        materials: &materials,
        decals: &[],
        texture: None,
        light: Light {
            direction: [s, s, 0.0],
            color: [1.0; 3],
            angular_radius: 0.05,
            ambient_up: [0.3; 3],
            ambient_down: [0.1; 3],
            up: [0.0, 1.0, 0.0],
        },
    };
    println!("triangles: {}", faces.len() / 3);
    let eye = [0.0f32, 0.0, 0.5];
    let f = 700.0;
    let viewmat = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, eye[2]],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let k = [[f, 0.0, 256.0], [0.0, f, 256.0], [0.0, 0.0, 1.0]];
    let camera = Camera::new(k, viewmat, 512, 512, 0.01, 100.0).unwrap();
    let mut group = c.benchmark_group("raytrace");
    group.sample_size(10);
    group.bench_function("bvh_build_100k", |b| b.iter(|| Scene::new(inputs).unwrap()));
    // A kept tree refit to a squashed copy: what each frame of `urhead synth` pays.
    let moved: Vec<f32> = vertices
        .chunks_exact(3)
        .flat_map(|p| [p[0] * 1.1, p[1] * 0.9, p[2] + 0.3 * p[0]])
        .collect();
    let mut kept = TriangleBvh::from_mesh(&vertices, &faces).unwrap();
    let moved_inputs = SceneInputs {
        vertices: &moved,
        ..inputs
    };
    group.bench_function("bvh_refit_100k", |b| {
        b.iter(|| {
            Scene::with_bvh(moved_inputs, &mut kept).unwrap();
        })
    });
    let scene = Scene::new(inputs).unwrap();
    for spp_side in [1u32, 4] {
        let settings = RenderSettings {
            samples_per_side: spp_side,
            edge_samples_per_side: 0,
            shadows: true,
            centre_hits: true,
            background: [1.0; 3],
            seed: 0,
        };
        let id = BenchmarkId::new("render_512_spp", spp_side * spp_side);
        group.bench_function(id, |b| b.iter(|| render(&scene, &camera, settings).unwrap()));
    }
    group.finish();
}

criterion_group!(benches, bench_raytrace);
criterion_main!(benches);
