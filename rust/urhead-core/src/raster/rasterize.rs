//! `rasterize`: perspective rasterization (forward) and the gradient of the barycentrics
//! with respect to world-space vertex positions (backward). Depth is an output for
//! occlusion tests and compositing only; it is not differentiated.

use rayon::prelude::*;

use super::bins::Bins;
use super::runs::{merge_runs, TriangleRuns};
use super::setup::{
    barycentrics, barycentrics_vjp, cross, plane_frame, setup_triangles, Hom, Setup, Viewport,
};
use super::{check_faces, check_tri_id, RasterImage, TILE_ROWS};
use crate::camera::Camera;
use crate::error::{check_finite, check_len, Error, Result};
use crate::mat3::map3;
use crate::memory::zeroed;
use crate::Real;

/// Rasterizes `faces (F, 3)` of `verts (V, 3)` (world space) through `camera`.
///
/// Errors (before any work): wrong shapes, an empty mesh, face indices out of range,
/// non-finite vertices.
pub fn rasterize_forward<T: Real>(verts: &[T], faces: &[i32], camera: &Camera) -> Result<RasterImage<T>> {
    Ok(rasterize_forward_kept(verts, faces, camera)?.0)
}

/// What a forward rasterization keeps for its backward: every triangle's setup (clipped,
/// snapped, its barycentric planes), which [`rasterize_backward_kept`] reads instead of
/// setting the triangles up again (a third of the backward's time at the paper's frame).
pub struct RasterSetup<T> {
    setup: Setup<T>,
    num_faces: usize,
    width: usize,
    height: usize,
}

/// [`rasterize_forward`], also returning the [`RasterSetup`] its backward can reuse.
pub fn rasterize_forward_kept<T: Real>(
    verts: &[T],
    faces: &[i32],
    camera: &Camera,
) -> Result<(RasterImage<T>, RasterSetup<T>)> {
    let hom = validate(verts, faces, camera)?;
    let vp = viewport(camera);
    let setup = setup_triangles::<T>(&hom, faces, &vp);
    let image = scan_tiles(&setup, &vp, T::c(camera.far as f64))?;
    let kept = RasterSetup {
        setup,
        num_faces: faces.len() / 3,
        width: vp.width,
        height: vp.height,
    };
    Ok((image, kept))
}

/// Gradient of a loss with respect to `verts (V, 3)` given its gradient `v_bary (H, W, 2)`
/// with respect to the barycentrics of [`rasterize_forward`], whose `tri_id (H, W)` is
/// passed back. The barycentrics are recomputed with the forward's own per-pixel function.
pub fn rasterize_backward<T: Real>(
    verts: &[T],
    faces: &[i32],
    camera: &Camera,
    tri_id: &[i32],
    v_bary: &[T],
) -> Result<Vec<T>> {
    backward(None, verts, faces, camera, tri_id, v_bary)
}

/// [`rasterize_backward`] with the setup `kept` by [`rasterize_forward_kept`] from the same
/// `verts`, `faces` and `camera` (the same gradient, bit for bit). A setup of another mesh
/// size or image size is refused; one of other vertices gives other gradients.
pub fn rasterize_backward_kept<T: Real>(
    kept: &RasterSetup<T>,
    verts: &[T],
    faces: &[i32],
    camera: &Camera,
    tri_id: &[i32],
    v_bary: &[T],
) -> Result<Vec<T>> {
    backward(Some(kept), verts, faces, camera, tri_id, v_bary)
}

/// Both backwards: checks, then the triangles' setup `kept` or made again.
fn backward<T: Real>(
    kept: Option<&RasterSetup<T>>,
    verts: &[T],
    faces: &[i32],
    camera: &Camera,
    tri_id: &[i32],
    v_bary: &[T],
) -> Result<Vec<T>> {
    let hom = validate(verts, faces, camera)?;
    let vp = viewport(camera);
    check_backward_inputs(faces, &vp, tri_id, v_bary)?;
    let made;
    let setup = match kept {
        Some(kept)
            if kept.num_faces != faces.len() / 3 || (kept.width, kept.height) != (vp.width, vp.height) =>
        {
            return Err(Error::Shape {
                arg: "setup",
                expected: format!(
                    "the setup of {} faces at {}×{}",
                    faces.len() / 3,
                    vp.width,
                    vp.height
                ),
                got: format!(
                    "one of {} faces at {}×{}",
                    kept.num_faces, kept.width, kept.height
                ),
            });
        }
        Some(kept) => &kept.setup,
        None => {
            made = setup_triangles::<T>(&hom, faces, &vp);
            &made
        }
    };
    backward_from_setup(&hom, setup, faces, camera, &vp, tri_id, v_bary)
}

fn check_backward_inputs<T: Real>(faces: &[i32], vp: &Viewport, tri_id: &[i32], v_bary: &[T]) -> Result<()> {
    let (w, h) = (vp.width, vp.height);
    check_tri_id(tri_id, h, w, faces.len() / 3)?;
    check_len("v_bary", v_bary, h * w * 2, &format!("(H, W, 2) = ({h}, {w}, 2)"))
}

fn backward_from_setup<T: Real>(
    hom: &[Hom],
    setup: &Setup<T>,
    faces: &[i32],
    camera: &Camera,
    vp: &Viewport,
    tri_id: &[i32],
    v_bary: &[T],
) -> Result<Vec<T>> {
    let (w, h) = (vp.width, vp.height);
    let num_faces = faces.len() / 3;

    // Per pixel, the gradient g of the raw plane values λ̃_i = e·(h'_j × h'_k) is needed
    // only through the moments M_i = Σ_pixels g_i·e, e = (ex, ey, 1); so each tile
    // accumulates 9 numbers per triangle and the vertex gradients follow per triangle.
    // A task per tile: the covered pixels crowd into the face's tiles, and rayon's split
    // of the range into a few runs left one thread waiting on the other (−0.20 ms, faster
    // in 139 of 150, a real step's backward alone).
    let runs: Vec<TriangleRuns<T>> = (0..vp.num_tiles())
        .into_par_iter()
        .with_max_len(1)
        .map(|tile| {
            let mut runs = TriangleRuns::new(9);
            for py in tile * TILE_ROWS..((tile + 1) * TILE_ROWS).min(h) {
                for px in 0..w {
                    let idx = py * w + px;
                    let (g1, g2) = (v_bary[2 * idx], v_bary[2 * idx + 1]);
                    let tri = tri_id[idx];
                    if tri < 0 || (g1 == T::zero() && g2 == T::zero()) {
                        continue;
                    }
                    let Some(planes) = setup.planes(tri as usize) else {
                        continue;
                    };
                    let (ex, ey) = planes.offset(px, py);
                    let Some(b) = barycentrics(planes.raw(ex, ey)) else {
                        continue;
                    };
                    let g = barycentrics_vjp(&b, [T::zero(), g1, g2]);
                    let slot = runs.slot(tri as u32);
                    for i in 0..3 {
                        slot[3 * i] += g[i] * ex;
                        slot[3 * i + 1] += g[i] * ey;
                        slot[3 * i + 2] += g[i];
                    }
                }
            }
            runs
        })
        .collect();
    let moments = merge_runs(&runs, num_faces, 9);

    let (fx, fy, cx, cy) = (
        camera.fx as f64,
        camera.fy as f64,
        camera.cx as f64,
        camera.cy as f64,
    );
    // Each face's three camera-space vertex gradients in parallel (each face's plane frame
    // is f64 work), then added to the vertices serially in face order: the same sums in
    // the same order as one serial loop.
    let per_face: Vec<Option<[[f64; 3]; 3]>> = moments
        .par_chunks_exact(9)
        .with_min_len(256)
        .enumerate()
        .map(|(f, m)| {
            if m.iter().all(|x| *x == T::zero()) {
                return None;
            }
            let planes = setup.planes(f)?;
            let tri = &faces[3 * f..3 * f + 3];
            let verts = [hom[tri[0] as usize], hom[tri[1] as usize], hom[tri[2] as usize]];
            let frame = plane_frame(&verts, planes.origin)?;
            let m: [[f64; 3]; 3] = map3(|i| map3(|k| m[3 * i + k].to_f64().unwrap_or(0.0) * frame.scale));
            let g_hom = hom_gradients(&m, &frame.hom);
            let (ox, oy) = (planes.origin[0] as f64, planes.origin[1] as f64);
            // h' = (X − ox·W, Y − oy·W, W) and h = (fx·x + cx·z, fy·y + cy·z, z).
            Some(g_hom.map(|g| {
                let (gx, gy, gw) = (g[0], g[1], g[2] - ox * g[0] - oy * g[1]);
                [fx * gx, fy * gy, cx * gx + cy * gy + gw]
            }))
        })
        .collect();
    let mut v_cam = vec![0.0f64; 3 * hom.len()];
    for (tri, grads) in faces.chunks_exact(3).zip(&per_face) {
        let Some(grads) = grads else { continue };
        for (&v, g) in tri.iter().zip(grads) {
            let v = v as usize;
            v_cam[3 * v] += g[0];
            v_cam[3 * v + 1] += g[1];
            v_cam[3 * v + 2] += g[2];
        }
    }
    Ok(camera_to_world_gradient(&v_cam, camera))
}

/// Gradients of the three (shifted) homogeneous vertices from the moments
/// `M_i = Σ g_i·e`: since `∂λ̃_0/∂h_1 = h_2 × e` and so on, `∂h_0 = M_1 × h_2 − M_2 × h_1`
/// and cyclically.
fn hom_gradients(m: &[[f64; 3]; 3], h: &[Hom; 3]) -> [[f64; 3]; 3] {
    map3(|k| {
        let (i, j) = ((k + 1) % 3, (k + 2) % 3);
        let a = cross(&m[i], &h[j]);
        let b = cross(&m[j], &h[i]);
        [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
    })
}

/// `v_world = Rᵀ·v_cam` for each vertex, cast to `T`.
pub(crate) fn camera_to_world_gradient<T: Real>(v_cam: &[f64], camera: &Camera) -> Vec<T> {
    let r = &camera.viewmat;
    v_cam
        .chunks_exact(3)
        .flat_map(|g| map3(|c| T::c(r[0][c] as f64 * g[0] + r[1][c] as f64 * g[1] + r[2][c] as f64 * g[2])))
        .collect()
}

fn viewport(camera: &Camera) -> Viewport {
    Viewport {
        width: camera.width as usize,
        height: camera.height as usize,
        near: camera.near as f64,
    }
}

/// Validates the mesh and returns homogeneous screen positions `K·(R·p + t)` in f64.
pub(crate) fn validate<T: Real>(verts: &[T], faces: &[i32], camera: &Camera) -> Result<Vec<Hom>> {
    if verts.len() % 3 != 0 {
        return Err(Error::Shape {
            arg: "verts",
            expected: "(V, 3)".into(),
            got: format!("{} elements", verts.len()),
        });
    }
    check_faces("faces", faces, verts.len() / 3, "V")?;
    check_finite("verts", verts)?;
    Ok(camera_homogeneous(verts, camera))
}

pub(crate) fn camera_homogeneous<T: Real>(verts: &[T], camera: &Camera) -> Vec<Hom> {
    let m = camera.viewmat.map(|row| row.map(|x| x as f64));
    let (fx, fy, cx, cy) = (
        camera.fx as f64,
        camera.fy as f64,
        camera.cx as f64,
        camera.cy as f64,
    );
    verts
        .chunks_exact(3)
        .map(|p| {
            let p = map3(|k| p[k].to_f64().unwrap_or(f64::NAN));
            let c = map3(|r| m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]);
            [fx * c[0] + cx * c[2], fy * c[1] + cy * c[2], c[2]]
        })
        .collect()
}

/// Scans every tile: per pixel the nearest covering triangle (equal depth → lower id),
/// skipping depths beyond `far`. The result is independent of scan order and threads.
pub(crate) fn scan_tiles<T: Real>(setup: &Setup<T>, vp: &Viewport, far: T) -> Result<RasterImage<T>> {
    let (w, h) = (vp.width, vp.height);
    let bins = Bins::new(setup, vp.num_tiles());
    let mut tri_id = zeroed("raster tri_id (H, W)", w * h)?;
    let mut bary = zeroed("raster bary (H, W, 2)", 2 * w * h)?;
    let mut depth = zeroed("raster depth (H, W)", w * h)?;
    tri_id
        .par_chunks_mut(TILE_ROWS * w)
        .zip(bary.par_chunks_mut(2 * TILE_ROWS * w))
        .zip(depth.par_chunks_mut(TILE_ROWS * w))
        .enumerate()
        .for_each(|(tile, ((ids, bs), ds))| {
            ids.fill(-1);
            ds.fill(T::infinity());
            let row0 = tile * TILE_ROWS;
            let row_end = row0 + ids.len() / w;
            for &r in bins.tile(tile) {
                let cov = setup.coverage_at(r);
                let Some(planes) = setup.planes(cov.tri as usize) else {
                    continue;
                };
                let tri = cov.tri as i32;
                let depth_floor = planes.depth_floor();
                let [e0, e1, e2] = cov.edges;
                let (x_first, x_last) = (cov.x0 as usize, cov.x1 as usize);
                for py in (cov.y0 as usize).max(row0)..=(cov.y1 as usize).min(row_end - 1) {
                    let (x0, y) = (cov.x0 as i64, py as i64);
                    let mut e = [
                        e0[0] * x0 + e0[1] * y + e0[2],
                        e1[0] * x0 + e1[1] * y + e1[2],
                        e2[0] * x0 + e2[1] * y + e2[2],
                    ];
                    let row = (py - row0) * w;
                    // Along the row the pixel centre's offset steps by exactly 1: it is
                    // an integer + 0.5 within the viewport (at most `MAX_IMAGE_SIDE` =
                    // 2^14 from the origin), exact in f32, so each step gives `offset`'s
                    // own value (−0.19 ms of a 3.5 ms raster; `row_terms` likewise).
                    let (mut ex, ey) = planes.offset(x_first, py);
                    let row_terms = planes.row_terms(ey);
                    for px in x_first..=x_last {
                        let i = row + px;
                        // A pixel already nearer than the whole triangle keeps its
                        // triangle: the barycentrics are not worth computing (most hidden
                        // faces of a closed head, behind the ones in front).
                        if (e[0] | e[1] | e[2]) >= 0 && ds[i] >= depth_floor {
                            if let Some(b) = barycentrics(planes.raw_on_row(ex, &row_terms)) {
                                let l = b.lambda;
                                let z = planes.depth_at(&l);
                                if z <= far && (z < ds[i] || (z == ds[i] && tri < ids[i])) {
                                    ids[i] = tri;
                                    ds[i] = z;
                                    bs[2 * i] = l[1];
                                    bs[2 * i + 1] = l[2];
                                }
                            }
                        }
                        e[0] += e0[0];
                        e[1] += e1[0];
                        e[2] += e2[0];
                        ex += T::one();
                    }
                }
            }
        });
    Ok(RasterImage {
        tri_id,
        bary,
        depth,
        width: w,
        height: h,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::sphere;

    /// The scan steps each pixel's offset and reuses a row's terms; the backward recomputes
    /// the barycentrics per pixel from `offset` and `raw`. They must agree bit for bit, in
    /// f32 and f64, or the backward differentiates other barycentrics than the forward's.
    #[test]
    fn scanned_barycentrics_are_the_per_pixel_ones_bit_for_bit() {
        fn check<T: Real>(verts: &[T], faces: &[i32], camera: &Camera) {
            let out = rasterize_forward(verts, faces, camera).unwrap();
            let setup =
                setup_triangles::<T>(&validate(verts, faces, camera).unwrap(), faces, &viewport(camera));
            let mut covered = 0;
            for (i, &tri) in out.tri_id.iter().enumerate() {
                if tri < 0 {
                    continue;
                }
                let planes = setup.planes(tri as usize).unwrap();
                let (ex, ey) = planes.offset(i % out.width, i / out.width);
                let b = barycentrics(planes.raw(ex, ey)).unwrap();
                assert_eq!(
                    out.bary[2 * i].to_f64().unwrap().to_bits(),
                    b.lambda[1].to_f64().unwrap().to_bits()
                );
                assert_eq!(
                    out.bary[2 * i + 1].to_f64().unwrap().to_bits(),
                    b.lambda[2].to_f64().unwrap().to_bits()
                );
                assert_eq!(
                    out.depth[i].to_f64().unwrap().to_bits(),
                    planes.depth_at(&b.lambda).to_f64().unwrap().to_bits()
                );
                covered += 1;
            }
            assert!(covered > 2000, "{covered} covered pixels");
        }
        let k = [[150.0, 0.0, 63.7], [0.0, 151.0, 58.2], [0.0, 0.0, 1.0]];
        let view = [
            [0.98, 0.0, 0.2, -0.1],
            [0.0, 1.0, 0.0, 0.05],
            [-0.2, 0.0, 0.98, 0.2],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let camera = Camera::new(k, view, 131, 117, 0.01, 100.0).unwrap();
        let (verts, faces) = sphere(24, 31, 0.03, 7);
        check(&verts, &faces, &camera);
        let verts32: Vec<f32> = verts.iter().map(|&x| x as f32).collect();
        check(&verts32, &faces, &camera);
    }

    /// The backward from the forward's kept setup is the one that sets up again, bit for
    /// bit; a setup of another image size is refused.
    #[test]
    fn the_kept_setup_gives_the_same_gradient_and_must_fit() {
        let k = [[90.0, 0.0, 40.3], [0.0, 92.0, 37.9], [0.0, 0.0, 1.0]];
        let view = [
            [1.0, 0.0, 0.0, 0.02],
            [0.0, 1.0, 0.0, -0.01],
            [0.0, 0.0, 1.0, 0.15],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let camera = Camera::new(k, view, 83, 77, 0.01, 100.0).unwrap();
        let (verts, faces) = sphere(12, 17, 0.05, 3);
        let (image, kept) = rasterize_forward_kept(&verts, &faces, &camera).unwrap();
        let v_bary: Vec<f64> = (0..image.bary.len())
            .map(|i| ((i * 37 % 101) as f64 - 50.0) / 50.0)
            .collect();
        let again = rasterize_backward(&verts, &faces, &camera, &image.tri_id, &v_bary).unwrap();
        let from_kept =
            rasterize_backward_kept(&kept, &verts, &faces, &camera, &image.tri_id, &v_bary).unwrap();
        assert!(again.iter().any(|g| *g != 0.0));
        assert_eq!(
            again.iter().map(|g| g.to_bits()).collect::<Vec<_>>(),
            from_kept.iter().map(|g| g.to_bits()).collect::<Vec<_>>()
        );
        let wider = Camera::new(k, view, 84, 77, 0.01, 100.0).unwrap();
        let (_, other) = rasterize_forward_kept(&verts, &faces, &wider).unwrap();
        let refused = rasterize_backward_kept(&other, &verts, &faces, &camera, &image.tri_id, &v_bary);
        assert!(matches!(refused, Err(Error::Shape { arg: "setup", .. })));
    }
}
