//! SSIM and L1 kernels against a direct (non-separable, f64) evaluation of the definition, its
//! gradient against central finite differences, and determinism across thread counts.

use urhead_core::error::Error;
use urhead_core::ssim::{
    masked_l1, masked_l1_with_grad, masked_ssim, masked_ssim_l1_with_grad, masked_ssim_with_grad,
    pixel_l1_with_grad, PixelL1Inputs, SsimInputs, C1, C2, SIGMA, WINDOW,
};
use urhead_core::testing::{on_threads, Rng};

/// Masked mean SSIM from the definition: a full 2-D window per pixel and channel.
fn direct_ssim(x: &[f64], y: &[f64], mask: Option<&[f64]>, h: usize, w: usize, c: usize) -> f64 {
    let half = (WINDOW / 2) as isize;
    let g: Vec<f64> = (0..WINDOW)
        .map(|i| (-((i as f64 - half as f64).powi(2)) / (2.0 * SIGMA * SIGMA)).exp())
        .collect();
    let g_sum: f64 = g.iter().sum();
    let (mut total, mut norm) = (0.0, 0.0);
    for i in 0..h {
        for j in 0..w {
            let m = mask.map_or(1.0, |m| m[i * w + j]);
            norm += m;
            let mut pixel = 0.0;
            for ch in 0..c {
                let mut e = [0.0; 5];
                for di in -half..=half {
                    for dj in -half..=half {
                        let (r, s) = (i as isize + di, j as isize + dj);
                        if r < 0 || s < 0 || r >= h as isize || s >= w as isize {
                            continue;
                        }
                        let wt = g[(di + half) as usize] * g[(dj + half) as usize] / (g_sum * g_sum);
                        let k = (r as usize * w + s as usize) * c + ch;
                        let (a, b) = (x[k], y[k]);
                        for (acc, v) in e.iter_mut().zip([a, b, a * a, b * b, a * b]) {
                            *acc += wt * v;
                        }
                    }
                }
                let [mx, my, exx, eyy, exy] = e;
                let num = (2.0 * mx * my + C1) * (2.0 * (exy - mx * my) + C2);
                let den = (mx * mx + my * my + C1) * ((exx - mx * mx) + (eyy - my * my) + C2);
                pixel += num / den;
            }
            total += m * pixel / c as f64;
        }
    }
    total / norm.max(1.0)
}

struct Case {
    x: Vec<f64>,
    y: Vec<f64>,
    mask: Option<Vec<f64>>,
    h: usize,
    w: usize,
    c: usize,
}

impl Case {
    /// A target and an image near it (as in training: a render close to the photo).
    fn new(h: usize, w: usize, c: usize, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let y: Vec<f64> = rng.vec(h * w * c, 0.0, 1.0);
        let x = y
            .iter()
            .map(|v| (v + rng.uniform(-0.2, 0.2)).clamp(0.0, 1.0))
            .collect();
        Self {
            x,
            y,
            mask: None,
            h,
            w,
            c,
        }
    }

    fn with_soft_mask(mut self, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        self.mask = Some(
            (0..self.h * self.w)
                .map(|_| {
                    if rng.uniform(0.0, 1.0) < 0.3 {
                        0.0
                    } else {
                        rng.uniform(0.0, 1.0)
                    }
                })
                .collect(),
        );
        self
    }

    fn inputs<'a>(&'a self, x: &'a [f64]) -> SsimInputs<'a, f64> {
        SsimInputs {
            image: x,
            target: &self.y,
            mask: self.mask.as_deref(),
            height: self.h,
            width: self.w,
            channels: self.c,
            image_channels: self.c,
        }
    }

    fn direct(&self, x: &[f64]) -> f64 {
        direct_ssim(x, &self.y, self.mask.as_deref(), self.h, self.w, self.c)
    }
}

fn cases() -> Vec<Case> {
    vec![
        Case::new(1, 1, 1, 1),
        Case::new(5, 7, 3, 2),
        Case::new(13, 11, 2, 3).with_soft_mask(4),
        Case::new(70, 29, 3, 5).with_soft_mask(6),
        Case::new(150, 17, 1, 7),
    ]
}

#[test]
fn value_matches_direct_definition() {
    for case in cases() {
        let ours = masked_ssim(&case.inputs(&case.x)).unwrap();
        let (fused, _) = masked_ssim_with_grad(&case.inputs(&case.x), 1.0).unwrap();
        let direct = case.direct(&case.x);
        assert!(
            (ours - direct).abs() < 1e-14,
            "{}x{}: {ours} vs {direct}",
            case.h,
            case.w
        );
        assert_eq!(ours.to_bits(), fused.to_bits());
    }
}

#[test]
fn gradient_matches_central_differences() {
    for case in cases() {
        let (_, grad) = masked_ssim_with_grad(&case.inputs(&case.x), 1.0).unwrap();
        let mut rng = Rng::new(11);
        for _ in 0..3 {
            let dir: Vec<f64> = rng.vec(case.x.len(), -1.0, 1.0);
            let eps = 1e-6;
            let shifted = |s: f64| -> Vec<f64> { case.x.iter().zip(&dir).map(|(x, d)| x + s * d).collect() };
            let (plus, minus) = (shifted(eps), shifted(-eps));
            let fd = (masked_ssim(&case.inputs(&plus)).unwrap() - masked_ssim(&case.inputs(&minus)).unwrap())
                / (2.0 * eps);
            let analytic: f64 = grad.iter().zip(&dir).map(|(g, d)| g * d).sum();
            let scale = analytic.abs().max(1e-3);
            assert!(
                (fd - analytic).abs() < 5e-7 * scale,
                "{}x{}: fd {fd} vs {analytic}",
                case.h,
                case.w
            );
        }
    }
}

/// The central difference of the masked SSIM along element `k` of the image.
fn element_difference(case: &Case, k: usize, eps: f64) -> f64 {
    let mut x = case.x.clone();
    x[k] += eps;
    let plus = masked_ssim(&case.inputs(&x)).unwrap();
    x[k] -= 2.0 * eps;
    let minus = masked_ssim(&case.inputs(&x)).unwrap();
    (plus - minus) / (2.0 * eps)
}

#[test]
fn gradient_elements_match_central_differences_near_borders() {
    let case = Case::new(9, 14, 2, 21).with_soft_mask(22);
    let (_, grad) = masked_ssim_with_grad(&case.inputs(&case.x), 1.0).unwrap();
    let eps = 1e-6;
    let mut worst: f64 = 0.0;
    for k in 0..case.x.len() {
        worst = worst.max((element_difference(&case, k, eps) - grad[k]).abs());
    }
    assert!(worst < 1e-9, "worst element error {worst}");
}

type Patches = [(std::ops::Range<usize>, std::ops::Range<usize>); 2];

/// Patches of rows × columns of a 140 × 16 image, one across the kernel's band boundary
/// (row 128), one band nearly empty.
const PATCHES: Patches = [(30..40, 3..6), (124..131, 10..12)];

fn in_patch(i: usize, j: usize) -> bool {
    PATCHES.iter().any(|(r, c)| r.contains(&i) && c.contains(&j))
}

/// The value against the definition, and the gradient against per-element differences
/// near the patches and zero beyond the reach of two blurs (10 pixels): exactly where the
/// kernel skips, to rounding where its band's columns still take in a pixel.
fn check_patchy(case: &Case, stride: usize) {
    let (value, grad) = masked_ssim_with_grad(&case.inputs(&case.x), 1.0).unwrap();
    let direct = case.direct(&case.x);
    assert!((value - direct).abs() < 1e-14, "{value} vs {direct}");
    assert_eq!(
        value.to_bits(),
        masked_ssim(&case.inputs(&case.x)).unwrap().to_bits()
    );
    let reach = (WINDOW - 1) as isize;
    let near_patch = |i: usize, j: usize| {
        PATCHES.iter().any(|(r, c)| {
            let (i, j) = (i as isize, j as isize);
            i >= r.start as isize - reach
                && i < r.end as isize + reach
                && j >= c.start as isize - reach
                && j < c.end as isize + reach
        })
    };
    let eps = 1e-6;
    let mut worst: f64 = 0.0;
    for k in 0..case.x.len() {
        let (i, j) = (k / case.c / case.w, k / case.c % case.w);
        if !near_patch(i, j) {
            assert!(
                grad[k].abs() < 1e-15,
                "element {k} (row {i}, column {j}): {}",
                grad[k]
            );
            continue;
        }
        if k % stride != 0 && (i + j) % 7 != 0 {
            continue; // one element in `stride` by differences, to keep the test short
        }
        worst = worst.max((element_difference(case, k, eps) - grad[k]).abs());
    }
    assert!(worst < 1e-9, "worst element error {worst}");
}

/// A mask of soft patches on a zero background, as a head's on its frame: the kernel
/// computes only on the columns the patches reach.
#[test]
fn a_mask_of_patches_matches_the_definition_everywhere() {
    let mut case = Case::new(140, 16, 1, 51);
    let mut rng = Rng::new(52);
    case.mask = Some(
        (0..case.h * case.w)
            .map(|p| {
                let v = rng.uniform(0.2, 1.0);
                if in_patch(p / case.w, p % case.w) {
                    v
                } else {
                    0.0
                }
            })
            .collect(),
    );
    check_patchy(&case, 2);
}

/// An image equal to its target but on patches, as a render on the photo's background: SSIM
/// is exactly 1 where a window sees no difference, and is computed only where one does.
#[test]
fn an_image_equal_to_its_target_but_on_patches_matches_the_definition_everywhere() {
    let mut case = Case::new(140, 16, 2, 53);
    for (k, (x, y)) in case.x.iter_mut().zip(&case.y).enumerate() {
        if !in_patch(k / case.c / case.w, k / case.c % case.w) {
            *x = *y;
        }
    }
    check_patchy(&case, 4);
}

#[test]
fn identical_images_score_one_with_zero_gradient() {
    let case = Case::new(20, 9, 3, 31);
    let (value, grad) = masked_ssim_with_grad(&case.inputs(&case.y), 1.0).unwrap();
    assert!((value - 1.0).abs() < 1e-14);
    assert!(grad.iter().all(|g| g.abs() < 1e-13));
}

#[test]
fn all_zero_mask_gives_zero_value_and_gradient() {
    let mut case = Case::new(12, 12, 3, 41);
    case.mask = Some(vec![0.0; 144]);
    let (value, grad) = masked_ssim_with_grad(&case.inputs(&case.x), 1.0).unwrap();
    assert_eq!(value, 0.0);
    assert!(grad.iter().all(|&g| g == 0.0));
}

/// Independent uniform f32 RGB images and a soft mask (for thread-count checks).
struct F32Images {
    x: Vec<f32>,
    y: Vec<f32>,
    mask: Vec<f32>,
    h: usize,
    w: usize,
}

impl F32Images {
    fn new(h: usize, w: usize, seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let y = rng.vec(h * w * 3, 0.0, 1.0);
        let x = rng.vec(h * w * 3, 0.0, 1.0);
        let mask = rng.vec(h * w, 0.0, 1.0);
        Self { x, y, mask, h, w }
    }

    fn inputs(&self) -> SsimInputs<'_, f32> {
        SsimInputs {
            image: &self.x,
            target: &self.y,
            mask: Some(&self.mask),
            height: self.h,
            width: self.w,
            channels: 3,
            image_channels: 3,
        }
    }
}

#[test]
fn thread_count_does_not_change_bits() {
    let images = F32Images::new(203, 37, 51);
    let inputs = images.inputs();
    let run = |threads: usize| on_threads(threads, || masked_ssim_with_grad(&inputs, 1.0).unwrap());
    let (v1, g1) = run(1);
    for threads in [2, 4] {
        let (v, g) = run(threads);
        assert_eq!(v.to_bits(), v1.to_bits());
        assert!(g.iter().zip(&g1).all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}

#[test]
fn bad_inputs_are_rejected_by_name() {
    let case = Case::new(4, 4, 3, 61);
    let mut x = case.x.clone();
    x[5] = f64::NAN;
    assert!(matches!(
        masked_ssim(&case.inputs(&x)),
        Err(Error::NonFinite {
            arg: "image",
            index: 5,
            ..
        })
    ));
    let short = &case.x[..10];
    assert!(matches!(
        masked_ssim(&case.inputs(short)),
        Err(Error::Shape { arg: "image", .. })
    ));
    let mut bad_mask = case;
    bad_mask.mask = Some(vec![1.5; 16]);
    let x = bad_mask.x.clone();
    assert!(matches!(
        masked_ssim_with_grad(&bad_mask.inputs(&x), 1.0),
        Err(Error::Invalid { arg: "mask", .. })
    ));
}

#[test]
fn l1_matches_definition_and_its_subgradient() {
    for case in cases() {
        let mut x = case.x.clone();
        x[0] = case.y[0]; // a zero difference: subgradient 0
        let (value, grad) = masked_l1_with_grad(&case.inputs(&x), 1.0).unwrap();
        assert_eq!(value.to_bits(), masked_l1(&case.inputs(&x)).unwrap().to_bits());
        let c = case.c;
        let mask = |k: usize| case.mask.as_ref().map_or(1.0, |m| m[k / c]);
        let norm: f64 = (0..x.len()).map(mask).sum::<f64>().max(1.0);
        let direct: f64 = (0..x.len())
            .map(|k| mask(k) * (x[k] - case.y[k]).abs())
            .sum::<f64>()
            / norm;
        assert!((value - direct).abs() < 1e-14, "{value} vs {direct}");
        for k in 0..x.len() {
            let d = x[k] - case.y[k];
            let expected = if d == 0.0 {
                0.0
            } else {
                mask(k) * d.signum() / norm
            };
            assert!(
                (grad[k] - expected).abs() <= 1e-13 * expected.abs(),
                "{} vs {expected}",
                grad[k]
            );
        }
    }
}

/// A loss term's weight scales the gradient (folded into the kernels' per-pixel scale, so
/// within roundings of the unweighted gradient times it: SSIM's passes through its blurs'
/// sums) and leaves the value alone; a non-finite weight is refused.
#[test]
fn a_weight_scales_the_gradient_only() {
    type Kernel = for<'a> fn(&SsimInputs<'a, f64>, f64) -> urhead_core::Result<(f64, Vec<f64>)>;
    let kernels: [(&str, Kernel); 2] = [("ssim", masked_ssim_with_grad), ("l1", masked_l1_with_grad)];
    for case in cases() {
        for (name, kernel) in kernels {
            let inputs = case.inputs(&case.x);
            let (value, grad) = kernel(&inputs, 1.0).unwrap();
            let largest = grad.iter().fold(0.0f64, |a, g| a.max(g.abs()));
            for weight in [0.64, -0.2, 0.0, 3.0] {
                let (weighted_value, weighted) = kernel(&inputs, weight).unwrap();
                assert_eq!(weighted_value.to_bits(), value.to_bits(), "{name}");
                let tolerance = 64.0 * f64::EPSILON * weight.abs() * largest;
                for (w, g) in weighted.iter().zip(&grad) {
                    let expected = weight * g;
                    assert!(
                        (w - expected).abs() <= tolerance,
                        "{name}, weight {weight}: {w} vs {expected}"
                    );
                }
            }
            for weight in [f64::NAN, f64::INFINITY] {
                assert!(matches!(
                    kernel(&inputs, weight),
                    Err(Error::Invalid { arg: "weight", .. })
                ));
            }
        }
    }
}

/// SSIM and L1 in one pass: each value and the gradient bit for bit those of the two
/// kernels apart (the gradient their sum), with a mask or without, an all-zero mask, f32
/// and f64 (the f32 case also across thread counts, on an image taller than one band).
#[test]
fn ssim_and_l1_in_one_pass_are_the_two_kernels_apart() {
    fn check<T: urhead_core::Real>(inputs: &SsimInputs<'_, T>, label: &str) {
        for (ssim_weight, l1_weight) in [(-0.2, 0.64), (1.0, 1.0), (0.0, -3.0), (0.5, 0.0)] {
            let (ssim, l1, grad) = masked_ssim_l1_with_grad(inputs, ssim_weight, l1_weight).unwrap();
            let (ssim_alone, ssim_grad) = masked_ssim_with_grad(inputs, ssim_weight).unwrap();
            let (l1_alone, l1_grad) = masked_l1_with_grad(inputs, l1_weight).unwrap();
            assert_eq!(
                ssim.to_f64().unwrap().to_bits(),
                ssim_alone.to_f64().unwrap().to_bits(),
                "{label}"
            );
            assert_eq!(
                l1.to_f64().unwrap().to_bits(),
                l1_alone.to_f64().unwrap().to_bits(),
                "{label}"
            );
            for (k, g) in grad.iter().enumerate() {
                let sum = ssim_grad[k] + l1_grad[k];
                assert_eq!(
                    g.to_f64().unwrap().to_bits(),
                    sum.to_f64().unwrap().to_bits(),
                    "{label} at {k}"
                );
            }
        }
    }
    for (i, case) in cases().into_iter().enumerate() {
        let mut x = case.x.clone();
        x[0] = case.y[0]; // a zero difference: the L1's subgradient 0
        check(&case.inputs(&x), &format!("case {i}"));
    }
    let mut zero_mask = Case::new(9, 8, 3, 71);
    zero_mask.mask = Some(vec![0.0; 72]);
    check(&zero_mask.inputs(&zero_mask.x), "all-zero mask");
    let (value_ssim, value_l1, grad) =
        masked_ssim_l1_with_grad(&zero_mask.inputs(&zero_mask.x), 1.0, 1.0).unwrap();
    assert_eq!((value_ssim, value_l1), (0.0, 0.0));
    assert!(grad.iter().all(|g| *g == 0.0));

    let images = F32Images::new(301, 23, 72);
    let inputs = images.inputs();
    check(&inputs, "f32");
    let run = |threads: usize| on_threads(threads, || masked_ssim_l1_with_grad(&inputs, -0.2, 0.64).unwrap());
    let (s1, l1, g1) = run(1);
    for threads in [2, 3] {
        let (s, l, g) = run(threads);
        assert_eq!((s.to_bits(), l.to_bits()), (s1.to_bits(), l1.to_bits()));
        assert!(g.iter().zip(&g1).all(|(a, b)| a.to_bits() == b.to_bits()));
    }
}

/// The one-pass SSIM + L1 refuses what either kernel refuses: non-finite weights, an image
/// wider than the target (SSIM compares whole images).
#[test]
fn ssim_and_l1_in_one_pass_refuse_bad_inputs() {
    let case = Case::new(6, 5, 3, 73);
    let inputs = case.inputs(&case.x);
    for (ssim_weight, l1_weight) in [(f64::NAN, 1.0), (1.0, f64::INFINITY), (1.0, f64::NAN)] {
        assert!(matches!(
            masked_ssim_l1_with_grad(&inputs, ssim_weight, l1_weight),
            Err(Error::Invalid { arg: "weight", .. })
        ));
    }
    let wide: Vec<f64> = vec![0.5; 6 * 5 * 4];
    let wider = SsimInputs {
        image: &wide,
        image_channels: 4,
        ..inputs
    };
    assert!(matches!(
        masked_ssim_l1_with_grad(&wider, 1.0, 1.0),
        Err(Error::Shape { arg: "image", .. })
    ));
}

/// The L1 of values at listed pixels (the normal loss) against its definition in f64: the
/// mask's weight where the target holds data, 0 on all-zero target pixels, sign(0) = 0,
/// repeated pixels counted per entry; and the same bits on 1–3 threads.
#[test]
fn pixel_l1_matches_its_definition() {
    let mut rng = Rng::new(81);
    let (n, c, count) = (500, 3, 20_000);
    let mut target: Vec<f64> = rng.vec(n * c, -1.0, 1.0);
    target[..30 * c].iter_mut().for_each(|t| *t = 0.0); // no data at the first 30 pixels
    let mask: Vec<f64> = rng.vec(n, 0.0, 1.0);
    let pixels: Vec<i64> = (0..count)
        .map(|_| rng.uniform(0.0, n as f64).floor() as i64)
        .collect();
    let mut values: Vec<f64> = rng.vec(count * c, -1.0, 1.0);
    values[..c].copy_from_slice(&target[pixels[0] as usize * c..][..c]);
    let inputs = PixelL1Inputs {
        values: &values,
        pixels: &pixels,
        target: &target,
        mask: &mask,
        channels: c,
    };
    let weight_of = |p: usize| {
        let x = pixels[p] as usize;
        if target[x * c..(x + 1) * c].iter().any(|t| *t != 0.0) {
            mask[x]
        } else {
            0.0
        }
    };
    let total_weight: f64 = (0..count).map(weight_of).sum();
    let direct: f64 = (0..count)
        .map(|p| {
            let x = pixels[p] as usize;
            weight_of(p)
                * (0..c)
                    .map(|k| (values[p * c + k] - target[x * c + k]).abs())
                    .sum::<f64>()
        })
        .sum::<f64>()
        / total_weight;
    let (value, grad) = pixel_l1_with_grad(&inputs, -0.5).unwrap();
    assert!((value - direct).abs() < 1e-12 * direct, "{value} vs {direct}");
    for p in 0..count {
        let x = pixels[p] as usize;
        for k in 0..c {
            let d = values[p * c + k] - target[x * c + k];
            let expected = -0.5 * weight_of(p) * if d == 0.0 { 0.0 } else { d.signum() } / total_weight;
            assert!((grad[p * c + k] - expected).abs() <= 1e-15, "{p}, {k}");
        }
    }
    assert!(grad[..c].iter().all(|g| *g == 0.0));
    let run = |threads: usize| on_threads(threads, || pixel_l1_with_grad(&inputs, 1.0).unwrap());
    let (v1, g1) = run(1);
    for threads in [2, 3] {
        let (v, g) = run(threads);
        assert_eq!(v.to_bits(), v1.to_bits());
        assert!(g.iter().zip(&g1).all(|(a, b)| a.to_bits() == b.to_bits()));
    }
    let bad = PixelL1Inputs {
        pixels: &[n as i64; 1],
        values: &values[..c],
        ..inputs
    };
    assert!(matches!(
        pixel_l1_with_grad(&bad, 1.0),
        Err(Error::IndexOutOfRange { arg: "pixels", .. })
    ));
}
