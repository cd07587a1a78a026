//! The mesh branch at FLAME size: a deformed sphere of 10 080 faces (5 112 vertices) at
//! 512 × 512 covering about 45 % of the image, sampling a 56-channel 2048² texture.
//!
//! `chain` runs rasterize → interpolate (UV) → texture (56 channels) → a fixed 56 → 3
//! linear map standing in for SH evaluation → antialias, forward and backward (the texture
//! gradient sparse). The other benchmarks time each op alone, and the covered pixels' maps
//! as a lookup then SH shading against the fused `sh_texture`.

use criterion::{criterion_group, criterion_main, Criterion};
use rayon::prelude::*;
use urhead_core::memory::zeroed;
use urhead_core::raster::{
    antialias_backward, antialias_forward, edge_topology, interpolate_backward, interpolate_forward,
    rasterize_backward, rasterize_backward_kept, rasterize_forward, rasterize_forward_kept,
    sh_texture_backward, sh_texture_forward, texture_backward, texture_forward, AntialiasInputs,
    ShTextureGradInputs, ShTextureInputs,
};
use urhead_core::shading::{shade_backward, shade_forward, ShadingInputs};
use urhead_core::testing::Rng;
use urhead_core::Camera;

const SIDE: u32 = 512;
const TEX: usize = 2048;
const CHANNELS: usize = 56;

struct Scene {
    verts: Vec<f32>,
    faces: Vec<i32>,
    uvs: Vec<f32>,
    topology: Vec<i32>,
    tex: Vec<f32>,
    /// `(CHANNELS, 3)`: the stand-in for SH evaluation.
    mix: Vec<f32>,
    camera: Camera,
}

/// A bumpy latitude–longitude sphere with per-vertex UVs (the seam is not split: the bench
/// only needs realistic UV footprints).
fn scene() -> Scene {
    let (n_lat, n_lon) = (70, 72);
    let mut verts = Vec::new();
    let mut uvs = Vec::new();
    for i in 0..=n_lat {
        let theta = std::f32::consts::PI * i as f32 / n_lat as f32;
        for j in 0..n_lon {
            let phi = 2.0 * std::f32::consts::PI * j as f32 / n_lon as f32;
            let r =
                0.115 * (1.0 + 0.08 * (3.0 * phi).sin() * (2.0 * theta).sin() + 0.05 * (5.0 * theta).cos());
            verts.extend([
                r * theta.sin() * phi.cos(),
                r * 1.2 * theta.cos(),
                0.6 + r * theta.sin() * phi.sin(),
            ]);
            uvs.extend([j as f32 / n_lon as f32, 1.0 - i as f32 / n_lat as f32]);
        }
    }
    let mut faces = Vec::new();
    for i in 0..n_lat {
        for j in 0..n_lon {
            let (a, b) = (i * n_lon + j, i * n_lon + (j + 1) % n_lon);
            let (c, d) = ((i + 1) * n_lon + j, (i + 1) * n_lon + (j + 1) % n_lon);
            faces.extend([a, c, b, b, c, d]);
        }
    }
    let f = 900.0;
    let k = [[f, 0.0, 256.0], [0.0, f, 256.0], [0.0, 0.0, 1.0]];
    let eye = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let camera = Camera::new(k, eye, SIDE, SIDE, 0.01, 100.0).unwrap();
    let mut rng = Rng::new(1);
    let tex = rng.vec(TEX * TEX * CHANNELS, -1.0, 1.0);
    let mix = rng.vec(CHANNELS * 3, -0.2, 0.2);
    let topology = edge_topology(&faces, verts.len() / 3).unwrap();
    Scene {
        verts,
        faces,
        uvs,
        topology,
        tex,
        mix,
        camera,
    }
}

/// `(N, CHANNELS) → (N, 3)` where covered, a constant background colour elsewhere
/// (parallel, like the SH evaluation it stands in for).
fn mix_forward(x: &[f32], mix: &[f32], tri_id: &[i32]) -> Vec<f32> {
    let mut out = vec![0.5f32; tri_id.len() * 3];
    out.par_chunks_mut(3)
        .zip(x.par_chunks_exact(CHANNELS))
        .zip(tri_id.par_iter())
        .for_each(|((o, px), &t)| {
            if t >= 0 {
                o.fill(0.0);
                for (k, v) in px.iter().enumerate() {
                    for c in 0..3 {
                        o[c] += v * mix[k * 3 + c];
                    }
                }
            }
        });
    out
}

/// Transpose of [`mix_forward`]: no gradient reaches background samples.
fn mix_backward(g: &[f32], mix: &[f32], tri_id: &[i32]) -> Vec<f32> {
    let mut out: Vec<f32> =
        zeroed("bench gradient", tri_id.len() * CHANNELS).expect("bench buffer fits in memory");
    out.par_chunks_mut(CHANNELS)
        .zip(g.par_chunks_exact(3))
        .zip(tri_id.par_iter())
        .for_each(|((o, g), &t)| {
            if t >= 0 {
                for (k, o) in o.iter_mut().enumerate() {
                    *o = g[0] * mix[k * 3] + g[1] * mix[k * 3 + 1] + g[2] * mix[k * 3 + 2];
                }
            }
        });
    out
}

fn chain(s: &Scene, g_out: &[f32]) -> usize {
    let (h, w) = (SIDE as usize, SIDE as usize);
    let (raster, kept) = rasterize_forward_kept(&s.verts, &s.faces, &s.camera).unwrap();
    let uv = interpolate_forward(&s.uvs, 2, &s.faces, &raster.tri_id, &raster.bary, h, w, None).unwrap();
    let sampled = texture_forward(&s.tex, TEX, TEX, CHANNELS, &uv).unwrap();
    let color = mix_forward(&sampled, &s.mix, &raster.tri_id);
    let aa = AntialiasInputs {
        color: &color,
        channels: 3,
        tri_id: &raster.tri_id,
        depth: &raster.depth,
        verts: &s.verts,
        faces: &s.faces,
        topology: &s.topology,
        camera: &s.camera,
    };
    let _image = antialias_forward(&aa).unwrap();
    let g_aa = antialias_backward(&aa, g_out, true, true).unwrap();
    let g_sampled = mix_backward(g_aa.v_color.as_ref().unwrap(), &s.mix, &raster.tri_id);
    let g_tex = texture_backward(&s.tex, TEX, TEX, CHANNELS, &uv, &g_sampled, true, true).unwrap();
    let g_interp = interpolate_backward(
        &s.uvs,
        2,
        &s.faces,
        &raster.tri_id,
        &raster.bary,
        h,
        w,
        None,
        g_tex.v_uv.as_ref().unwrap(),
        false,
        true,
    )
    .unwrap();
    let g_verts = rasterize_backward_kept(
        &kept,
        &s.verts,
        &s.faces,
        &s.camera,
        &raster.tri_id,
        g_interp.v_bary.as_ref().unwrap(),
    )
    .unwrap();
    g_verts.len() + g_tex.v_tex.map_or(0, |t| t.nnz)
}

fn bench_raster(c: &mut Criterion) {
    let s = scene();
    let (h, w) = (SIDE as usize, SIDE as usize);
    let raster = rasterize_forward(&s.verts, &s.faces, &s.camera).unwrap();
    let covered = raster.tri_id.iter().filter(|&&t| t >= 0).count();
    eprintln!(
        "scene: {} faces, {} vertices, {:.1} % of {SIDE}² covered, texture {TEX}² × {CHANNELS}",
        s.faces.len() / 3,
        s.verts.len() / 3,
        100.0 * covered as f64 / (h * w) as f64
    );
    let mut rng = Rng::new(2);
    let g_bary = rng.vec::<f32>(h * w * 2, -1.0, 1.0);
    let g_uv_out = rng.vec::<f32>(h * w * 2, -1.0, 1.0);
    let g_rgb = rng.vec::<f32>(h * w * 3, -1.0, 1.0);
    // The covered pixels in increasing order, as `Avatar.shade_mesh` lists them.
    let covered_pixels: Vec<i64> = (0..(h * w) as i64)
        .filter(|&p| raster.tri_id[p as usize] >= 0)
        .collect();
    let mut g_sampled = rng.vec::<f32>(h * w * CHANNELS, -1.0, 1.0);
    for (g, &t) in g_sampled.chunks_exact_mut(CHANNELS).zip(&raster.tri_id) {
        if t < 0 {
            g.fill(0.0);
        }
    }
    let g_uv_covered = rng.vec::<f32>(covered_pixels.len() * 2, -1.0, 1.0);
    let uv = interpolate_forward(&s.uvs, 2, &s.faces, &raster.tri_id, &raster.bary, h, w, None).unwrap();
    let color = mix_forward(
        &texture_forward(&s.tex, TEX, TEX, CHANNELS, &uv).unwrap(),
        &s.mix,
        &raster.tri_id,
    );
    let aa = AntialiasInputs {
        color: &color,
        channels: 3,
        tri_id: &raster.tri_id,
        depth: &raster.depth,
        verts: &s.verts,
        faces: &s.faces,
        topology: &s.topology,
        camera: &s.camera,
    };

    let mut group = c.benchmark_group("raster");
    group.sample_size(20);
    group.bench_function("chain_forward_backward", |b| b.iter(|| chain(&s, &g_rgb)));
    group.bench_function("rasterize_forward", |b| {
        b.iter(|| rasterize_forward(&s.verts, &s.faces, &s.camera).unwrap())
    });
    group.bench_function("rasterize_backward", |b| {
        b.iter(|| rasterize_backward(&s.verts, &s.faces, &s.camera, &raster.tri_id, &g_bary).unwrap())
    });
    let (_, kept) = rasterize_forward_kept(&s.verts, &s.faces, &s.camera).unwrap();
    group.bench_function("rasterize_backward_kept_setup", |b| {
        b.iter(|| {
            rasterize_backward_kept(&kept, &s.verts, &s.faces, &s.camera, &raster.tri_id, &g_bary).unwrap()
        })
    });
    group.bench_function("interpolate_forward", |b| {
        b.iter(|| interpolate_forward(&s.uvs, 2, &s.faces, &raster.tri_id, &raster.bary, h, w, None).unwrap())
    });
    group.bench_function("interpolate_backward", |b| {
        b.iter(|| {
            interpolate_backward(
                &s.uvs,
                2,
                &s.faces,
                &raster.tri_id,
                &raster.bary,
                h,
                w,
                None,
                &g_uv_out,
                true,
                true,
            )
            .unwrap()
        })
    });
    let listed = Some(covered_pixels.as_slice());
    group.bench_function("interpolate_forward_covered_pixels", |b| {
        b.iter(|| {
            interpolate_forward(&s.uvs, 2, &s.faces, &raster.tri_id, &raster.bary, h, w, listed).unwrap()
        })
    });
    group.bench_function("interpolate_backward_covered_pixels", |b| {
        b.iter(|| {
            interpolate_backward(
                &s.uvs,
                2,
                &s.faces,
                &raster.tri_id,
                &raster.bary,
                h,
                w,
                listed,
                &g_uv_covered,
                true,
                true,
            )
            .unwrap()
        })
    });
    group.bench_function("texture_forward", |b| {
        b.iter(|| texture_forward(&s.tex, TEX, TEX, CHANNELS, &uv).unwrap())
    });
    group.bench_function("texture_backward", |b| {
        b.iter(|| texture_backward(&s.tex, TEX, TEX, CHANNELS, &uv, &g_sampled, true, true).unwrap())
    });
    // The mesh branch's pixel maps: the lookup at the covered pixels then SH shading (and
    // the normal's columns), against the fused op; forward alone as a frame renders it,
    // and forward + backward (rows' gradient and UV gradient) as a training step does.
    let uv_covered =
        interpolate_forward(&s.uvs, 2, &s.faces, &raster.tri_id, &raster.bary, h, w, listed).unwrap();
    let n_covered = covered_pixels.len();
    let dirs: Vec<f32> = (0..n_covered)
        .flat_map(|i| {
            let x = (i % 97) as f32 / 97.0 - 0.5;
            let len = (x * x + 1.0).sqrt();
            [x / len, 0.0, -1.0 / len]
        })
        .collect();
    let v_pixel_maps = rng.vec::<f32>(n_covered * 6, -1.0, 1.0);
    let v_rgb: Vec<f32> = v_pixel_maps
        .chunks_exact(6)
        .flat_map(|v| [v[0], v[1], v[2]])
        .collect();
    let v_normal: Vec<f32> = v_pixel_maps
        .chunks_exact(6)
        .flat_map(|v| [v[3], v[4], v[5]])
        .collect();
    let pixel_maps = ShTextureInputs {
        tex: &s.tex,
        height: TEX,
        width: TEX,
        channels: CHANNELS,
        uv: &uv_covered,
        dirs: &dirs,
        degree: 3,
        extra: 48..51,
    };
    let lookup_then_shade = |backward: bool| {
        let rows = texture_forward(&s.tex, TEX, TEX, CHANNELS, &uv_covered).unwrap();
        let shading = ShadingInputs {
            coeffs: &rows,
            dirs: &dirs,
            stride: CHANNELS,
            degree: 3,
        };
        let rgb = shade_forward(&shading).unwrap();
        if !backward {
            return rgb.len();
        }
        let mut v_rows = shade_backward(&shading, &v_rgb, None).unwrap();
        for (row, v) in v_rows
            .chunks_exact_mut(CHANNELS)
            .zip(v_pixel_maps.chunks_exact(6))
        {
            row[48..51].copy_from_slice(&v[3..]);
        }
        let g = texture_backward(&s.tex, TEX, TEX, CHANNELS, &uv_covered, &v_rows, false, true).unwrap();
        g.v_uv.map_or(0, |v| v.len()) + v_rows.len()
    };
    let fused = |backward: bool| {
        let out = sh_texture_forward(&pixel_maps, backward, backward).unwrap();
        if !backward {
            return out.rgb.len() + out.extra.len();
        }
        let g = sh_texture_backward(
            &ShTextureGradInputs {
                uv: &uv_covered,
                dirs: &dirs,
                degree: 3,
                channels: CHANNELS,
                extra: 48..51,
                raw_rgb: out.raw_rgb.as_deref().unwrap(),
                slopes: out.slopes.as_deref(),
                v_rgb: Some(&v_rgb),
                v_extra: Some(&v_normal),
            },
            true,
        )
        .unwrap();
        g.v_uv.map_or(0, |v| v.len()) + g.v_rows.map_or(0, |v| v.len())
    };
    group.bench_function("pixel_maps_lookup_then_shade_forward", |b| {
        b.iter(|| lookup_then_shade(false))
    });
    group.bench_function("pixel_maps_sh_texture_forward", |b| b.iter(|| fused(false)));
    group.bench_function("pixel_maps_lookup_then_shade_forward_backward", |b| {
        b.iter(|| lookup_then_shade(true))
    });
    group.bench_function("pixel_maps_sh_texture_forward_backward", |b| {
        b.iter(|| fused(true))
    });
    group.bench_function("antialias_forward", |b| {
        b.iter(|| antialias_forward(&aa).unwrap())
    });
    group.bench_function("antialias_backward", |b| {
        b.iter(|| antialias_backward(&aa, &g_rgb, true, true).unwrap())
    });
    group.bench_function("topology", |b| {
        b.iter(|| edge_topology(&s.faces, s.verts.len() / 3).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench_raster);
criterion_main!(benches);
