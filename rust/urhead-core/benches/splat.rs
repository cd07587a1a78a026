//! Gaussian splatting at 512²: projection (SH degree 3) + tile compositing, forward and
//! forward+backward, for 10k / 30k / 100k head-sized Gaussians.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use urhead_core::splat::{
    project_backward, project_forward, rasterize_backward, rasterize_forward, ProjectGradOutputs,
    ProjectNeeds, SyntheticSplat,
};
use urhead_core::testing::Rng;

const SIZE: u32 = 512;

fn bench_splat(c: &mut Criterion) {
    let mut group = c.benchmark_group("splat");
    group.sample_size(20);
    for n in [10_000usize, 30_000, 100_000] {
        let scene = SyntheticSplat::<f32>::head(n, SIZE, 0.75, 1);
        let inputs = scene.inputs(Some(3));
        let px = (SIZE * SIZE) as usize;
        let mut rng = Rng::new(2);
        let v_image = rng.vec::<f32>(px * 3, -1.0, 1.0);
        let v_t = rng.vec::<f32>(px, -1.0, 1.0);
        let bg = [1.0f32; 3];
        let run = |backward: bool| {
            let proj = project_forward(&scene.camera, &inputs).unwrap();
            let raster = scene.raster_inputs(&proj, Some(&bg), None, 0.01);
            let fwd = rasterize_forward(&raster).unwrap();
            if backward {
                let rg = rasterize_backward(&raster, &fwd.binning, Some(&v_image), Some(&v_t), None).unwrap();
                let grads = ProjectGradOutputs {
                    v_means2d: Some(&rg.v_means2d),
                    v_conics: Some(&rg.v_conics),
                    v_colors: Some(&rg.v_colors),
                };
                let needs = ProjectNeeds {
                    means: true,
                    quats: true,
                    scales: true,
                    sh: true,
                };
                project_backward(&scene.camera, &inputs, &grads, &needs).unwrap();
            }
            fwd.image[0]
        };
        group.bench_function(BenchmarkId::new("forward", n), |b| b.iter(|| run(false)));
        group.bench_function(BenchmarkId::new("forward_backward", n), |b| b.iter(|| run(true)));
    }
    group.finish();
}

criterion_group!(benches, bench_splat);
criterion_main!(benches);
