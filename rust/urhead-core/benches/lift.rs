//! The Gaussian lift of a training iteration: 24k Gaussians on a FLAME-size mesh (5023
//! vertices, random faces and barycentrics, near-rotation skinning frames), f32; forward
//! and forward + backward (gradients to vertices, rotations, normals and lifts).

use criterion::{criterion_group, criterion_main, Criterion};
use urhead_core::lift::{lift_backward, lift_forward, LiftGradOutputs, LiftInputs, LiftNeeds};
use urhead_core::testing::Rng;

const GAUSSIANS: usize = 24_000;
const VERTS: usize = 5023;

fn bench_lift(c: &mut Criterion) {
    let mut rng = Rng::new(0);
    let verts: Vec<f32> = rng.vec(VERTS * 3, -0.1, 0.1);
    let mut rotations = Vec::with_capacity(VERTS * 9);
    for _ in 0..VERTS {
        for r in 0..3 {
            for k in 0..3 {
                let eye = if r == k { 1.0 } else { 0.0 };
                rotations.push((eye + rng.uniform(-0.1, 0.1)) as f32);
            }
        }
    }
    let face_verts: Vec<i32> = (0..GAUSSIANS * 3)
        .map(|_| (rng.next_u64() % VERTS as u64) as i32)
        .collect();
    let mut bary = Vec::with_capacity(GAUSSIANS * 3);
    for _ in 0..GAUSSIANS {
        let (a, b) = (rng.uniform(0.0, 0.5), rng.uniform(0.0, 0.5));
        bary.extend([a as f32, b as f32, (1.0 - a - b) as f32]);
    }
    let normals: Vec<f32> = rng.vec(GAUSSIANS * 3, -1.0, 1.0);
    let lift: Vec<f32> = rng.vec(GAUSSIANS, -0.004, 0.004);
    let centre = [0.0f32, 0.0, -0.7];
    let inputs = LiftInputs {
        verts: &verts,
        rotations: &rotations,
        face_verts: &face_verts,
        bary: &bary,
        normals: &normals,
        lift: &lift,
        centre: &centre,
    };
    let v_means: Vec<f32> = rng.vec(GAUSSIANS * 3, -1.0, 1.0);
    let v_quats: Vec<f32> = rng.vec(GAUSSIANS * 4, -1.0, 1.0);
    let grads = LiftGradOutputs {
        v_means: Some(&v_means),
        v_normals: None,
        v_quats: Some(&v_quats),
    };
    let needs = LiftNeeds {
        verts: true,
        rotations: true,
        normals: true,
        lift: true,
    };
    let mut group = c.benchmark_group("lift_24k_f32");
    group.bench_function("forward", |b| b.iter(|| lift_forward(&inputs).unwrap()));
    group.bench_function("forward_backward", |b| {
        b.iter(|| {
            lift_forward(&inputs).unwrap();
            lift_backward(&inputs, &grads, &needs).unwrap()
        })
    });
    group.finish();
}

criterion_group!(benches, bench_lift);
criterion_main!(benches);
