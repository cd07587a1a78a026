//! The avatar's Gaussians over its mesh at 512²: `front + T·back` with the mesh's RGBA as
//! `back` (S = 4), f32; forward and forward + backward (both gradients).

use criterion::{criterion_group, criterion_main, Criterion};
use urhead_core::composite::{composite_backward, composite_forward, CompositeInputs};
use urhead_core::testing::Rng;

const PIXELS: usize = 512 * 512;

fn bench_composite(c: &mut Criterion) {
    let mut rng = Rng::new(0);
    let front: Vec<f32> = rng.vec(3 * PIXELS, 0.0, 1.0);
    let transmittance: Vec<f32> = rng.vec(PIXELS, 0.0, 1.0);
    let back: Vec<f32> = rng.vec(4 * PIXELS, 0.0, 1.0);
    let v_out: Vec<f32> = rng.vec(3 * PIXELS, -1.0, 1.0);
    let inputs = CompositeInputs {
        front: &front,
        transmittance: &transmittance,
        back: &back,
        back_channels: 4,
    };
    let mut group = c.benchmark_group("composite_512x512_f32");
    group.bench_function("forward", |b| b.iter(|| composite_forward(&inputs).unwrap()));
    group.bench_function("forward_backward", |b| {
        b.iter(|| {
            composite_forward(&inputs).unwrap();
            composite_backward(&inputs, &v_out, true, true).unwrap()
        })
    });
    group.finish();
}

criterion_group!(benches, bench_composite);
criterion_main!(benches);
