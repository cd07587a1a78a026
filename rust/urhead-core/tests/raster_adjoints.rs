//! Mesh rasterizer adjoints against float64 central differences along random directions,
//! the float32 forward against the float64 forward, and bitwise determinism across
//! thread counts.

use urhead_core::raster::{
    antialias_backward, antialias_backward_blends, antialias_forward, antialias_forward_blends,
    edge_topology, interpolate_backward, interpolate_forward, rasterize_backward, rasterize_forward,
    rasterize_uv, texture_backward, texture_forward, AntialiasInputs, RasterImage, SilhouetteBlends,
};
use urhead_core::testing::{on_threads, record_stability, sphere, Rng};
use urhead_core::Camera;

const W: u32 = 48;
const H: u32 = 40;

fn camera() -> Camera {
    let k = [[40.0, 0.0, 23.3], [0.0, 41.0, 19.6], [0.0, 0.0, 1.0]];
    let (c, s) = (0.2f32.cos(), 0.2f32.sin());
    // A small rotation about y, then a shift: the camera looks at the sphere off-axis.
    let view = [
        [c, 0.0, s, -0.5],
        [0.0, 1.0, 0.0, 0.1],
        [-s, 0.0, c, 0.3],
        [0.0, 0.0, 0.0, 1.0],
    ];
    Camera::new(k, view, W, H, 0.01, 100.0).unwrap()
}

/// The antialias inputs of `color` over a raster of the mesh.
fn antialias_inputs<'a>(
    color: &'a [f64],
    channels: usize,
    raster: &'a RasterImage<f64>,
    mesh: (&'a [f64], &'a [i32], &'a [i32]),
    camera: &'a Camera,
) -> AntialiasInputs<'a, f64> {
    let (verts, faces, topology) = mesh;
    AntialiasInputs {
        color,
        channels,
        tri_id: &raster.tri_id,
        depth: &raster.depth,
        verts,
        faces,
        topology,
        camera,
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn shifted(x: &[f64], d: &[f64], t: f64) -> Vec<f64> {
    x.iter().zip(d).map(|(a, b)| a + t * b).collect()
}

/// Central difference of `f` along `d` against the analytic directional derivative.
fn check(analytic: &[f64], d: &[f64], f: impl Fn(f64) -> f64, h: f64, tol: f64, what: &str) {
    let fd = (f(h) - f(-h)) / (2.0 * h);
    let an = dot(analytic, d);
    assert!(
        (an - fd).abs() <= tol * (1.0 + fd.abs()),
        "{what}: analytic {an} vs finite difference {fd}"
    );
}

#[test]
fn rasterize_gradient_matches_central_differences() {
    let cam = camera();
    for seed in 0..3 {
        let (verts, faces) = sphere(8, 12, 0.05, seed);
        let mut rng = Rng::new(100 + seed);
        let weights: Vec<f64> = rng.vec((W * H * 2) as usize, -1.0, 1.0);
        let out = rasterize_forward(&verts, &faces, &cam).unwrap();
        assert!(out.tri_id.iter().filter(|&&t| t >= 0).count() > 300);
        let grad = rasterize_backward(&verts, &faces, &cam, &out.tri_id, &weights).unwrap();
        let d: Vec<f64> = rng.vec(verts.len(), -1.0, 1.0);
        let loss = |t: f64| {
            let o = rasterize_forward(&shifted(&verts, &d, t), &faces, &cam).unwrap();
            assert_eq!(o.tri_id, out.tri_id, "coverage changed under the perturbation");
            dot(&o.bary, &weights)
        };
        check(&grad, &d, loss, 1e-7, 5e-9, "rasterize");
    }
}

#[test]
fn interpolate_gradients_match_central_differences() {
    let cam = camera();
    let (verts, faces) = sphere(8, 12, 0.05, 3);
    let raster = rasterize_forward(&verts, &faces, &cam).unwrap();
    let (h, w, c) = (H as usize, W as usize, 3);
    let mut rng = Rng::new(7);
    let attr: Vec<f64> = rng.vec(verts.len() / 3 * c, -1.0, 1.0);
    let weights: Vec<f64> = rng.vec(h * w * c, -1.0, 1.0);
    let g = interpolate_backward(
        &attr,
        c,
        &faces,
        &raster.tri_id,
        &raster.bary,
        h,
        w,
        None,
        &weights,
        true,
        true,
    )
    .unwrap();
    let loss = |a: &[f64], b: &[f64]| {
        dot(
            &interpolate_forward(a, c, &faces, &raster.tri_id, b, h, w, None).unwrap(),
            &weights,
        )
    };
    let d: Vec<f64> = rng.vec(attr.len(), -1.0, 1.0);
    check(
        g.v_attr.as_ref().unwrap(),
        &d,
        |t| loss(&shifted(&attr, &d, t), &raster.bary),
        1e-6,
        1e-10,
        "v_attr",
    );
    let d: Vec<f64> = rng.vec(raster.bary.len(), -1.0, 1.0);
    check(
        g.v_bary.as_ref().unwrap(),
        &d,
        |t| loss(&attr, &shifted(&raster.bary, &d, t)),
        1e-6,
        1e-9,
        "v_bary",
    );
}

#[test]
fn texture_gradients_match_central_differences() {
    let (ht, wt, c, n) = (7, 9, 3, 300);
    let mut rng = Rng::new(11);
    let tex: Vec<f64> = rng.vec(ht * wt * c, -1.0, 1.0);
    let uv: Vec<f64> = rng.vec(2 * n, -0.1, 1.1);
    let weights: Vec<f64> = rng.vec(n * c, -1.0, 1.0);
    let g = texture_backward(&tex, ht, wt, c, &uv, &weights, true, true).unwrap();
    let loss = |t: &[f64], u: &[f64]| dot(&texture_forward(t, ht, wt, c, u).unwrap(), &weights);
    // Densify the sparse texel gradient: it must be exactly linear in the texture.
    let sparse = g.v_tex.unwrap();
    let mut dense = vec![0.0; tex.len()];
    for k in 0..sparse.nnz {
        let (r, col) = (
            sparse.indices[k] as usize,
            sparse.indices[sparse.nnz + k] as usize,
        );
        for ch in 0..c {
            dense[(r * wt + col) * c + ch] = sparse.values[k * c + ch];
        }
    }
    let d: Vec<f64> = rng.vec(tex.len(), -1.0, 1.0);
    check(
        &dense,
        &d,
        |t| loss(&shifted(&tex, &d, t), &uv),
        1e-6,
        1e-9,
        "v_tex",
    );
    let d: Vec<f64> = rng.vec(uv.len(), -1.0, 1.0);
    check(
        g.v_uv.as_ref().unwrap(),
        &d,
        |t| loss(&tex, &shifted(&uv, &d, t)),
        1e-8,
        1e-7,
        "v_uv",
    );
}

#[test]
fn kept_antialias_blends_out_of_range_are_named_errors() {
    let good = [0.0, 1.0, 0.0, 1.0, 0.0, 0.25, 0.1, -0.5, 0.2, 0.5];
    assert_eq!(SilhouetteBlends::from_packed(&good, 2, 2).unwrap().len(), 1);
    let mut cases = Vec::new();
    for (k, bad) in [(0, 2.0), (1, -1.0), (2, 0.5), (3, f64::NAN), (4, 2.0)] {
        let mut b = good;
        b[k] = bad;
        cases.push(b.to_vec());
    }
    cases.push(good[..9].to_vec()); // not (B, 10)
    for b in cases {
        let err = SilhouetteBlends::from_packed(&b, 2, 2).unwrap_err().to_string();
        assert!(err.contains("blends"), "{err}");
    }
    // Blends that fit a larger image are refused by a smaller image's backward.
    let cam = camera();
    let (verts, faces) = sphere(8, 12, 0.05, 20);
    let topology = edge_topology(&faces, verts.len() / 3).unwrap();
    let raster = rasterize_forward(&verts, &faces, &cam).unwrap();
    let pixels = raster.tri_id.len();
    let color = vec![0.5f64; pixels * 3];
    let far = [
        pixels as f64 + 1.0,
        pixels as f64 + 2.0,
        0.0,
        1.0,
        0.0,
        0.25,
        0.1,
        -0.5,
        0.2,
        0.5,
    ];
    let blends = SilhouetteBlends::from_packed(&far, pixels + 8, verts.len() / 3).unwrap();
    let inputs = antialias_inputs(&color, 3, &raster, (&verts, &faces, &topology), &cam);
    let err = antialias_backward_blends(&inputs, &color, true, true, &blends).unwrap_err();
    assert!(err.to_string().contains("blends"), "{err}");
}

#[test]
fn antialias_gradients_match_central_differences() {
    let cam = camera();
    let (h, w, c) = (H as usize, W as usize, 3);
    for seed in 0..3 {
        let (verts, faces) = sphere(8, 12, 0.05, 20 + seed);
        let topology = edge_topology(&faces, verts.len() / 3).unwrap();
        let raster = rasterize_forward(&verts, &faces, &cam).unwrap();
        let mut rng = Rng::new(200 + seed);
        let color: Vec<f64> = rng.vec(h * w * c, 0.0, 1.0);
        let weights: Vec<f64> = rng.vec(h * w * c, -1.0, 1.0);
        let inputs = |v: &'_ [f64], col: &'_ [f64]| -> Vec<f64> {
            let r = rasterize_forward(v, &faces, &cam).unwrap();
            assert_eq!(r.tri_id, raster.tri_id, "coverage changed under the perturbation");
            antialias_forward(&antialias_inputs(col, c, &r, (v, &faces, &topology), &cam)).unwrap()
        };
        let base = antialias_inputs(&color, c, &raster, (&verts, &faces, &topology), &cam);
        let out = antialias_forward(&base).unwrap();
        assert!(out.iter().zip(&color).filter(|(a, b)| a != b).count() > 20);
        let g = antialias_backward(&base, &weights, true, true).unwrap();
        // The forward's blends, kept (and passed through their packed form, as from
        // Python), give the backward's gradients bit for bit without a second search.
        let (kept_out, blends) = antialias_forward_blends(&base).unwrap();
        assert_eq!(kept_out, out);
        assert!(blends.len() > 20);
        let packed = SilhouetteBlends::from_packed(&blends.packed(), h * w, verts.len() / 3).unwrap();
        assert_eq!(packed, blends);
        let kept = antialias_backward_blends(&base, &weights, true, true, &packed).unwrap();
        assert_eq!((&kept.v_color, &kept.v_verts), (&g.v_color, &g.v_verts));
        let d: Vec<f64> = rng.vec(color.len(), -1.0, 1.0);
        check(
            g.v_color.as_ref().unwrap(),
            &d,
            |t| dot(&inputs(&verts, &shifted(&color, &d, t)), &weights),
            1e-3, // linear in the colour: a large step only reduces rounding noise
            1e-9,
            "v_color",
        );
        // The position gradient uses a 1e-3 px guard on the edge's extent across the
        // pixel pair, so it matches the exact derivative to about that relative size.
        let d: Vec<f64> = rng.vec(verts.len(), -1.0, 1.0);
        check(
            g.v_verts.as_ref().unwrap(),
            &d,
            |t| dot(&inputs(&shifted(&verts, &d, t), &color), &weights),
            1e-7,
            2e-3,
            "v_verts",
        );
    }
}

#[test]
fn float32_forward_agrees_with_float64() {
    let cam = camera();
    let (verts, faces) = sphere(10, 14, 0.05, 5);
    let verts32: Vec<f32> = verts.iter().map(|&x| x as f32).collect();
    let rounded: Vec<f64> = verts32.iter().map(|&x| x as f64).collect();
    let a = rasterize_forward(&verts32, &faces, &cam).unwrap();
    let b = rasterize_forward(&rounded, &faces, &cam).unwrap();
    assert_eq!(a.tri_id, b.tri_id);
    let worst = a
        .bary
        .iter()
        .zip(&b.bary)
        .map(|(x, y)| (*x as f64 - y).abs())
        .fold(0.0, f64::max);
    assert!(worst < 2e-6, "worst barycentric error {worst}");
}

/// Every output and gradient of the whole chain, as bits.
fn chain_bits() -> Vec<u64> {
    let cam = camera();
    let (h, w, c) = (H as usize, W as usize, 4);
    let (verts64, faces) = sphere(12, 16, 0.03, 9);
    let verts: Vec<f32> = verts64.iter().map(|&x| x as f32).collect();
    let mut rng = Rng::new(3);
    let uv_attr: Vec<f32> = rng.vec(verts.len() / 3 * 2, 0.0, 1.0);
    let tex: Vec<f32> = rng.vec(32 * 24 * c, 0.0, 1.0);
    let raster = rasterize_forward(&verts, &faces, &cam).unwrap();
    let uv = interpolate_forward(&uv_attr, 2, &faces, &raster.tri_id, &raster.bary, h, w, None).unwrap();
    let color = texture_forward(&tex, 32, 24, c, &uv).unwrap();
    let topology = edge_topology(&faces, verts.len() / 3).unwrap();
    let aa = AntialiasInputs {
        color: &color,
        channels: c,
        tri_id: &raster.tri_id,
        depth: &raster.depth,
        verts: &verts,
        faces: &faces,
        topology: &topology,
        camera: &cam,
    };
    let out = antialias_forward(&aa).unwrap();
    let g_out: Vec<f32> = rng.vec(out.len(), -1.0, 1.0);
    let g_aa = antialias_backward(&aa, &g_out, true, true).unwrap();
    let g_tex = texture_backward(&tex, 32, 24, c, &uv, g_aa.v_color.as_ref().unwrap(), true, true).unwrap();
    let g_interp = interpolate_backward(
        &uv_attr,
        2,
        &faces,
        &raster.tri_id,
        &raster.bary,
        h,
        w,
        None,
        g_tex.v_uv.as_ref().unwrap(),
        true,
        true,
    )
    .unwrap();
    let g_verts = rasterize_backward(
        &verts,
        &faces,
        &cam,
        &raster.tri_id,
        g_interp.v_bary.as_ref().unwrap(),
    )
    .unwrap();
    let uv_raster = rasterize_uv(&uv_attr, &faces, 64, 64).unwrap();
    let sparse = g_tex.v_tex.unwrap();
    let floats = [
        &raster.bary,
        &raster.depth,
        &uv,
        &color,
        &out,
        g_aa.v_verts.as_ref().unwrap(),
        &sparse.values,
        g_interp.v_attr.as_ref().unwrap(),
        &g_verts,
        &uv_raster.bary,
    ];
    let mut bits: Vec<u64> = floats
        .iter()
        .flat_map(|v| v.iter().map(|x| x.to_bits() as u64))
        .collect();
    bits.extend(raster.tri_id.iter().chain(&uv_raster.tri_id).map(|&t| t as u64));
    bits.extend(sparse.indices.iter().map(|&i| i as u64));
    bits
}

#[test]
fn whole_chain_is_bitwise_identical_for_any_thread_count() {
    let run = |threads: usize| on_threads(threads, chain_bits);
    let reference = run(1);
    for threads in [2, 3, 4] {
        let bits = run(threads);
        let differing = bits.iter().zip(&reference).filter(|(a, b)| a != b).count()
            + bits.len().abs_diff(reference.len());
        record_stability(
            27,
            "Rust mesh chain: elements whose bits differ from the 1-thread run",
            "raster_adjoints::whole_chain_is_bitwise_identical_for_any_thread_count",
            differing as f64,
            0.0,
        );
        assert!(bits == reference, "{threads} threads differ from 1");
    }
}
