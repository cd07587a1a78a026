//! rotate_normalize at a training iteration's covered pixels: 75k near-rotations applied to
//! map normals, f32; forward and forward + backward to both inputs, and the transposed
//! forward alone (camera rays into the rest frame).

use criterion::{criterion_group, criterion_main, Criterion};
use urhead_core::rotate::{rotate_normalize_backward, rotate_normalize_forward, RotateInputs, RotateNeeds};
use urhead_core::testing::Rng;

const ROWS: usize = 75_000;

fn bench_rotate(c: &mut Criterion) {
    let mut rng = Rng::new(0);
    let mut rotations: Vec<f32> = rng.vec(ROWS * 9, -0.2, 0.2);
    for row in rotations.chunks_exact_mut(9) {
        for k in [0, 4, 8] {
            row[k] += 1.0;
        }
    }
    let vectors: Vec<f32> = rng.vec(ROWS * 3, -1.0, 1.0);
    let v_out: Vec<f32> = rng.vec(ROWS * 3, -1.0, 1.0);
    let inputs = RotateInputs {
        rotations: &rotations,
        vectors: &vectors,
        transpose: false,
        rows: None,
    };
    let needs = RotateNeeds {
        rotations: true,
        vectors: true,
    };
    let mut group = c.benchmark_group("rotate_normalize_75k_f32");
    group.bench_function("forward", |b| {
        b.iter(|| rotate_normalize_forward(&inputs).unwrap())
    });
    group.bench_function("forward_backward", |b| {
        b.iter(|| {
            rotate_normalize_forward(&inputs).unwrap();
            rotate_normalize_backward(&inputs, &v_out, &needs).unwrap()
        })
    });
    let transposed = RotateInputs {
        transpose: true,
        ..inputs
    };
    group.bench_function("forward_transposed", |b| {
        b.iter(|| rotate_normalize_forward(&transposed).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench_rotate);
criterion_main!(benches);
