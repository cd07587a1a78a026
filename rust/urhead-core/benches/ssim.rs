//! Masked SSIM of a 512 × 512 × 3 f32 image (the training resolution): value only, and
//! value with gradient (the training loop's forward + backward); the same for masked L1.

use criterion::{criterion_group, criterion_main, Criterion};
use urhead_core::ssim::{masked_l1, masked_l1_with_grad, masked_ssim, masked_ssim_with_grad, SsimInputs};
use urhead_core::testing::Rng;

const SIDE: usize = 512;
const CHANNELS: usize = 3;

fn bench_ssim(c: &mut Criterion) {
    let mut rng = Rng::new(0);
    let target: Vec<f32> = rng.vec(SIDE * SIDE * CHANNELS, 0.0, 1.0);
    let image: Vec<f32> = target
        .iter()
        .map(|t| (t + rng.uniform(-0.1, 0.1) as f32).clamp(0.0, 1.0))
        .collect();
    // A head-sized elliptical mask covering about half the frame.
    let mask: Vec<f32> = (0..SIDE * SIDE)
        .map(|p| {
            let (i, j) = (
                (p / SIDE) as f32 / SIDE as f32 - 0.5,
                (p % SIDE) as f32 / SIDE as f32 - 0.5,
            );
            if (i / 0.45).powi(2) + (j / 0.35).powi(2) < 1.0 {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let inputs = SsimInputs {
        image: &image,
        target: &target,
        mask: Some(&mask),
        height: SIDE,
        width: SIDE,
        channels: CHANNELS,
        image_channels: CHANNELS,
    };
    let mut group = c.benchmark_group("ssim_512x512x3_f32");
    group.bench_function("forward", |b| b.iter(|| masked_ssim(&inputs).unwrap()));
    group.bench_function("forward_backward", |b| {
        b.iter(|| masked_ssim_with_grad(&inputs, 1.0).unwrap())
    });
    group.finish();
    let mut group = c.benchmark_group("l1_512x512x3_f32");
    group.bench_function("forward", |b| b.iter(|| masked_l1(&inputs).unwrap()));
    group.bench_function("forward_backward", |b| {
        b.iter(|| masked_l1_with_grad(&inputs, 1.0).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench_ssim);
criterion_main!(benches);
