//! Batched SH shading of a training iteration's covered pixels: 90k samples, rows of the
//! packed 56-channel map table, degree 3, f32; forward and forward + backward.

use criterion::{criterion_group, criterion_main, Criterion};
use urhead_core::shading::{shade_backward, shade_forward, ShadingInputs};
use urhead_core::testing::Rng;

const SAMPLES: usize = 90_000;
const STRIDE: usize = 56;

fn bench_shading(c: &mut Criterion) {
    let mut rng = Rng::new(0);
    let coeffs: Vec<f32> = rng.vec(SAMPLES * STRIDE, -0.5, 0.5);
    let mut dirs = Vec::with_capacity(SAMPLES * 3);
    for _ in 0..SAMPLES {
        let d = [
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(0.2, 1.0),
        ];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        dirs.extend(d.map(|x| (x / len) as f32));
    }
    let v_rgb: Vec<f32> = rng.vec(SAMPLES * 3, -1.0, 1.0);
    let inputs = ShadingInputs {
        coeffs: &coeffs,
        dirs: &dirs,
        stride: STRIDE,
        degree: 3,
    };
    let mut group = c.benchmark_group("sh_shade_90k_deg3_f32");
    group.bench_function("forward", |b| b.iter(|| shade_forward(&inputs).unwrap()));
    group.bench_function("forward_backward", |b| {
        b.iter(|| {
            shade_forward(&inputs).unwrap();
            shade_backward(&inputs, &v_rgb, None).unwrap()
        })
    });
    group.finish();
}

criterion_group!(benches, bench_shading);
criterion_main!(benches);
