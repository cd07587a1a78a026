//! Splatting adjoint (projection + SH + tile compositing, chained) against float64 central
//! differences along random directions; the AVX2 path against the scalar path bit for bit;
//! the same bits for any thread count.

use urhead_core::splat::lanes::{Emu, Lanes};
use urhead_core::splat::{
    project_backward, project_forward, rasterize_backward_with, rasterize_forward_with, ProjectGradOutputs,
    ProjectNeeds, SplatReal, SyntheticSplat,
};
use urhead_core::testing::{on_threads, record_stability, Rng};
use urhead_core::Real;

const SIZE: u32 = 48;

/// Image, transmittance and every input gradient of `loss = Σ w_img·image + Σ w_t·T`.
struct Rendered<T> {
    image: Vec<T>,
    transmittance: Vec<T>,
    v_means: Vec<T>,
    v_quats: Vec<T>,
    v_scales: Vec<T>,
    v_opacities: Vec<T>,
    v_sh: Vec<T>,
}

fn scene<T: SplatReal>(n: usize, seed: u64) -> SyntheticSplat<T> {
    let mut s = SyntheticSplat::<T>::head(n, SIZE, 0.75, seed);
    // Several pixels wide at this resolution, so each Gaussian covers many pixels.
    for v in &mut s.scales {
        *v *= T::c(6.0);
    }
    s
}

fn render<L: Lanes>(
    s: &SyntheticSplat<L::Elem>,
    depth_map: Option<&[L::Elem]>,
    w_img: &[L::Elem],
    w_t: &[L::Elem],
) -> Rendered<L::Elem>
where
    L::Elem: SplatReal,
{
    let inputs = s.inputs(Some(3));
    let proj = project_forward(&s.camera, &inputs).unwrap();
    let bg = [0.2, 0.5, 0.9].map(L::Elem::c);
    let raster = s.raster_inputs(&proj, Some(&bg), depth_map, L::Elem::c(0.01));
    let fwd = rasterize_forward_with::<L>(&raster).unwrap();
    let rg = rasterize_backward_with::<L>(&raster, &fwd.binning, Some(w_img), Some(w_t), None).unwrap();
    let needs = ProjectNeeds {
        means: true,
        quats: true,
        scales: true,
        sh: true,
    };
    let grads = ProjectGradOutputs {
        v_means2d: Some(&rg.v_means2d),
        v_conics: Some(&rg.v_conics),
        v_colors: Some(&rg.v_colors),
    };
    let pg = project_backward(&s.camera, &inputs, &grads, &needs).unwrap();
    Rendered {
        image: fwd.image,
        transmittance: fwd.transmittance,
        v_means: pg.v_means.unwrap(),
        v_quats: pg.v_quats.unwrap(),
        v_scales: pg.v_scales.unwrap(),
        v_opacities: rg.v_opacities,
        v_sh: pg.v_sh.unwrap(),
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Directional derivative of the loss along a random direction of one input, analytic vs
/// central differences.
fn check_input(
    name: &str,
    s: &SyntheticSplat<f64>,
    depth_map: Option<&[f64]>,
    pick: fn(&mut SyntheticSplat<f64>) -> &mut Vec<f64>,
    analytic: fn(&Rendered<f64>) -> &Vec<f64>,
    seed: u64,
) {
    let px = (SIZE * SIZE) as usize;
    let mut rng = Rng::new(seed);
    let w_img = rng.vec::<f64>(px * 3, -1.0, 1.0);
    let w_t = rng.vec::<f64>(px, -1.0, 1.0);
    let base = render::<Emu<f64>>(s, depth_map, &w_img, &w_t);
    let len = pick(&mut s.clone()).len();
    let dir = rng.vec::<f64>(len, -1.0, 1.0);
    let loss_at = |t: f64| {
        let mut p = s.clone();
        for (v, d) in pick(&mut p).iter_mut().zip(&dir) {
            *v += t * d;
        }
        let r = render::<Emu<f64>>(&p, depth_map, &w_img, &w_t);
        dot(&r.image, &w_img) + dot(&r.transmittance, &w_t)
    };
    // Small enough that no pixel's alpha crosses the 1/255 cut-off inside ±h (the
    // rendering is discontinuous there by design), large enough for float64 round-off.
    let h = 1e-8;
    let fd = (loss_at(h) - loss_at(-h)) / (2.0 * h);
    let an = dot(analytic(&base), &dir);
    assert!(
        (an - fd).abs() <= 1e-5 * (1.0 + fd.abs()),
        "{name}: analytic {an} vs finite differences {fd}"
    );
    assert!(fd.abs() > 1e-3, "{name}: direction carries no signal ({fd})");
}

fn check_all(depth_map: Option<&[f64]>) {
    let s = scene::<f64>(40, 3);
    check_input("means", &s, depth_map, |p| &mut p.means, |r| &r.v_means, 1);
    check_input("quats", &s, depth_map, |p| &mut p.quats, |r| &r.v_quats, 2);
    check_input("scales", &s, depth_map, |p| &mut p.scales, |r| &r.v_scales, 3);
    check_input(
        "opacities",
        &s,
        depth_map,
        |p| &mut p.opacities,
        |r| &r.v_opacities,
        4,
    );
    check_input("sh", &s, depth_map, |p| &mut p.sh, |r| &r.v_sh, 5);
}

#[test]
fn gradients_match_finite_differences() {
    check_all(None);
}

#[test]
fn gradients_match_finite_differences_with_occlusion() {
    // A tilted plane through the head: roughly half of the Gaussians are behind it.
    let depth: Vec<f64> = (0..SIZE * SIZE)
        .map(|p| 0.72 + 0.002 * (p % SIZE) as f64)
        .collect();
    check_all(Some(&depth));
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2", target_feature = "fma"))]
#[test]
fn avx2_and_scalar_paths_agree_bitwise() {
    use urhead_core::splat::lanes::Avx2;
    let s = scene::<f32>(300, 8);
    let px = (SIZE * SIZE) as usize;
    let mut rng = Rng::new(4);
    let w_img = rng.vec::<f32>(px * 3, -1.0, 1.0);
    let w_t = rng.vec::<f32>(px, -1.0, 1.0);
    let depth: Vec<f32> = (0..px)
        .map(|p| 0.7 + 0.003 * (p % SIZE as usize) as f32)
        .collect();
    for dm in [None, Some(depth.as_slice())] {
        let a = render::<Avx2>(&s, dm, &w_img, &w_t);
        let b = render::<Emu<f32>>(&s, dm, &w_img, &w_t);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.image), bits(&b.image));
        assert_eq!(bits(&a.transmittance), bits(&b.transmittance));
        assert_eq!(bits(&a.v_means), bits(&b.v_means));
        assert_eq!(bits(&a.v_opacities), bits(&b.v_opacities));
        assert_eq!(bits(&a.v_sh), bits(&b.v_sh));
        assert!(a.image.iter().any(|&v| v != a.image[0]), "render is not trivial");
    }
}

/// NUMERICS.md case 27: the same bits on 1, 2 and 4 threads, repeated.
#[test]
fn case27_same_bits_for_any_thread_count() {
    let s = scene::<f32>(500, 9);
    let px = (SIZE * SIZE) as usize;
    let mut rng = Rng::new(6);
    let w_img = rng.vec::<f32>(px * 3, -1.0, 1.0);
    let w_t = rng.vec::<f32>(px, -1.0, 1.0);
    let run = |threads: usize| {
        on_threads(threads, || {
            render::<<f32 as SplatReal>::Fast>(&s, None, &w_img, &w_t)
        })
    };
    let reference = run(1);
    for threads in [1, 2, 4, 2, 1, 4] {
        let r = run(threads);
        let differing = |a: &[f32], b: &[f32]| {
            a.iter()
                .zip(b)
                .filter(|(x, y)| x.to_bits() != y.to_bits())
                .count()
        };
        let count = differing(&r.image, &reference.image)
            + differing(&r.v_means, &reference.v_means)
            + differing(&r.v_quats, &reference.v_quats)
            + differing(&r.v_sh, &reference.v_sh);
        record_stability(
            27,
            "Rust splatting: elements whose bits differ from the 1-thread run",
            "splat_gradients::case27_same_bits_for_any_thread_count",
            count as f64,
            0.0,
        );
        assert!(r
            .image
            .iter()
            .zip(&reference.image)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(r
            .v_means
            .iter()
            .zip(&reference.v_means)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(r
            .v_quats
            .iter()
            .zip(&reference.v_quats)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(r
            .v_sh
            .iter()
            .zip(&reference.v_sh)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}

/// With a mesh depth map, a Gaussian is not listed in the tiles where it lies behind the
/// mesh at every pixel, and only there; the gradients are those of listing it everywhere
/// (the backward replayed on the uncut lists), the same values.
#[test]
fn gaussians_hidden_in_a_whole_tile_are_not_listed_there() {
    let s = scene::<f32>(400, 10);
    let px = (SIZE * SIZE) as usize;
    let mut rng = Rng::new(11);
    let w_img = rng.vec::<f32>(px * 3, -1.0, 1.0);
    let w_t = rng.vec::<f32>(px, -1.0, 1.0);
    // A plane through the head, nearer on the left: hides some Gaussians in whole tiles.
    let depth: Vec<f32> = (0..px)
        .map(|p| 0.66 + 0.004 * (p % SIZE as usize) as f32)
        .collect();
    let inputs = s.inputs(Some(3));
    let proj = project_forward(&s.camera, &inputs).unwrap();
    let raster = |depth_map| s.raster_inputs(&proj, None, depth_map, 0.01);
    type L = <f32 as SplatReal>::Fast;
    let occluded = raster(Some(&depth));
    let culled = rasterize_forward_with::<L>(&occluded).unwrap().binning;
    let uncut = rasterize_forward_with::<L>(&raster(None)).unwrap().binning;
    // Each tile's list is the uncut one without the Gaussians deeper than all its limits.
    let tile = 16usize;
    let mut dropped = 0;
    for t in 0..uncut.tiles_x * uncut.tiles_y {
        let (tx, ty) = (t % uncut.tiles_x, t / uncut.tiles_x);
        let deepest = (ty * tile..((ty + 1) * tile).min(SIZE as usize))
            .flat_map(|y| (tx * tile..((tx + 1) * tile).min(SIZE as usize)).map(move |x| (x, y)))
            .map(|(x, y)| depth[y * SIZE as usize + x] + 0.01)
            .fold(f32::NEG_INFINITY, f32::max);
        let list = |b: &urhead_core::splat::Binning| {
            b.tile_gaussians[b.tile_offsets[t] as usize..b.tile_offsets[t + 1] as usize].to_vec()
        };
        let expected: Vec<u32> = list(&uncut)
            .into_iter()
            .filter(|&g| proj.depths[g as usize] <= deepest)
            .collect();
        dropped += list(&uncut).len() - expected.len();
        assert_eq!(list(&culled), expected, "tile {t}");
    }
    assert!(
        dropped > 0 && dropped < uncut.num_intersections(),
        "{dropped} dropped"
    );
    let a = rasterize_backward_with::<L>(&occluded, &culled, Some(&w_img), Some(&w_t), None).unwrap();
    let b = rasterize_backward_with::<L>(&occluded, &uncut, Some(&w_img), Some(&w_t), None).unwrap();
    assert_eq!(a.v_means2d, b.v_means2d);
    assert_eq!(a.v_conics, b.v_conics);
    assert_eq!(a.v_colors, b.v_colors);
    assert_eq!(a.v_opacities, b.v_opacities);
    assert!(
        a.v_opacities.iter().any(|&v| v != 0.0),
        "the occluded render has gradients"
    );
}
