//! Sparse Adam on a 2048² × 56 UV atlas with 20k / 100k touched texels in UV patches,
//! with float32 and with bfloat16 moments.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use urhead_core::adam::{sparse_adam_step, AdamConfig, Bf16, Moment, SparseAdamState};
use urhead_core::testing::Rng;

const ROWS: usize = 2048 * 2048;
const CHANNELS: usize = 56;

fn bench_moments<M: Moment>(c: &mut Criterion, name: &str) {
    let mut param = vec![0f32; ROWS * CHANNELS];
    let mut exp_avg = vec![M::default(); ROWS * CHANNELS];
    let mut exp_avg_sq = vec![M::default(); ROWS * CHANNELS];
    let mut steps = vec![0i32; ROWS];
    let lr = vec![1e-3f32; CHANNELS];
    let config = AdamConfig {
        beta1: 0.9,
        beta2: 0.999,
        eps: 1e-15,
    };
    let mut group = c.benchmark_group(format!("sparse_adam_2048x2048x56_{name}"));
    for touched in [20_000usize, 100_000] {
        let mut rng = Rng::new(touched as u64);
        let stride = ROWS / touched;
        let rows: Vec<i64> = (0..touched)
            .map(|i| (i * stride + (rng.next_u64() as usize % stride)) as i64)
            .collect();
        let grads = rng.vec::<f32>(touched * CHANNELS, -1.0, 1.0);
        group.bench_function(BenchmarkId::from_parameter(touched), |b| {
            b.iter(|| {
                let mut state = SparseAdamState {
                    param: &mut param,
                    exp_avg: &mut exp_avg,
                    exp_avg_sq: &mut exp_avg_sq,
                    steps: &mut steps,
                    channels: CHANNELS,
                };
                sparse_adam_step(&mut state, &rows, &grads, &lr, &config, None).unwrap()
            })
        });
    }
    group.finish();
}

fn bench_adam(c: &mut Criterion) {
    bench_moments::<f32>(c, "f32_moments");
    bench_moments::<Bf16>(c, "bf16_moments");
}

criterion_group!(benches, bench_adam);
criterion_main!(benches);
