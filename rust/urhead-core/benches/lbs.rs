//! LBS forward and forward+backward at FLAME size (5023 vertices, 400 betas, 5 joints).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use urhead_core::lbs::{lbs_backward, lbs_forward, LbsGradOutputs, LbsInputs, LbsNeeds};
use urhead_core::testing::{Rng, SyntheticLbs};

fn bench_lbs(c: &mut Criterion) {
    let tables = SyntheticLbs::<f32>::new(5023, 400, 5, 7);
    let model = tables.model();
    let mut group = c.benchmark_group("lbs");
    for batch in [1usize, 16] {
        let mut rng = Rng::new(1);
        let betas = rng.vec::<f32>(batch * 400, -2.0, 2.0);
        let pose = rng.vec::<f32>(batch * 15, -0.5, 0.5);
        let transl = rng.vec::<f32>(batch * 3, -0.1, 0.1);
        let inputs = LbsInputs {
            betas: &betas,
            pose: &pose,
            transl: Some(&transl),
            batch,
        };
        let v_verts = rng.vec::<f32>(batch * 5023 * 3, -1.0, 1.0);
        let grads = LbsGradOutputs {
            v_verts: Some(&v_verts),
            ..Default::default()
        };
        let needs = LbsNeeds {
            betas: true,
            pose: true,
            transl: true,
            ..Default::default()
        };
        group.bench_function(BenchmarkId::new("forward", batch), |bch| {
            bch.iter(|| lbs_forward(&model, &inputs).unwrap())
        });
        group.bench_function(BenchmarkId::new("forward_backward", batch), |bch| {
            bch.iter(|| {
                let fwd = lbs_forward(&model, &inputs).unwrap();
                lbs_backward(&model, &inputs, &fwd.saved(), &grads, &needs).unwrap()
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_lbs);
criterion_main!(benches);
