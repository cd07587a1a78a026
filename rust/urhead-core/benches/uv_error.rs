//! accumulate_uv_error on a training frame's layout: a 512² f32 image, a head-sized disc of
//! ~75k covered pixels inside a mask that reaches ~4k pixels beyond it (hair), into 256²
//! grids (the UV varying smoothly across the image); and the whole-image nearest-covered-pixel search of the error breakdown.

use criterion::{criterion_group, criterion_main, Criterion};
use urhead_core::testing::Rng;
use urhead_core::uv_error::{accumulate_uv_error, nearest_covered, UvErrorInputs};

const SIDE: usize = 512;
const GRID: usize = 256;

fn bench_uv_error(c: &mut Criterion) {
    let mut rng = Rng::new(0);
    let image: Vec<f32> = rng.vec(SIDE * SIDE * 3, 0.0, 1.0);
    let target: Vec<f32> = rng.vec(SIDE * SIDE * 3, 0.0, 1.0);
    let centre = SIDE as f64 / 2.0;
    let radius = |p: usize| ((p / SIDE) as f64 - centre).hypot((p % SIDE) as f64 - centre);
    let covered: Vec<bool> = (0..SIDE * SIDE).map(|p| radius(p) < 155.0).collect();
    let mask: Vec<f32> = (0..SIDE * SIDE)
        .map(|p| if radius(p) < 159.5 { 1.0 } else { 0.0 })
        .collect();
    let pixels: Vec<i64> = (0..SIDE * SIDE)
        .filter(|&p| covered[p])
        .map(|p| p as i64)
        .collect();
    // The UV a pixel sees varies smoothly across the image, as on a face.
    let uv: Vec<f32> = pixels
        .iter()
        .flat_map(|&p| {
            let (row, col) = (p as usize / SIDE, p as usize % SIDE);
            let jitter = rng.uniform(-1e-3, 1e-3);
            [
                col as f64 / SIDE as f64 + jitter,
                1.0 - row as f64 / SIDE as f64 - jitter,
            ]
            .map(|x| x as f32)
        })
        .collect();
    let inputs = UvErrorInputs {
        image: &image,
        target: &target,
        mask: &mask,
        pixels: &pixels,
        uv: &uv,
        height: SIDE,
        width: SIDE,
    };
    let (mut error, mut count) = (vec![0.0; GRID * GRID], vec![0.0; GRID * GRID]);
    c.bench_function("accumulate_uv_error_512_f32", |b| {
        b.iter(|| accumulate_uv_error(&inputs, GRID, &mut error, &mut count).unwrap())
    });
    c.bench_function("nearest_covered_512", |b| {
        b.iter(|| nearest_covered(&covered, SIDE, SIDE).unwrap())
    });
}

criterion_group!(benches, bench_uv_error);
criterion_main!(benches);
