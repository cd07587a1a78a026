//! Ray tracer: validation, determinism across thread counts, and geometric outputs on
//! scenes whose answer is known in closed form.

use urhead_core::raytrace::{render, Light, RenderOutput, RenderSettings, Scene, SceneInputs, TriangleBvh};
use urhead_core::testing::on_threads;
use urhead_core::{Camera, Error};

const LIGHT: Light = Light {
    direction: [0.0, 0.6, 0.8],
    color: [1.0; 3],
    angular_radius: 0.1,
    ambient_up: [0.2; 3],
    ambient_down: [0.1; 3],
    up: [0.0, 1.0, 0.0],
};
const MATERIAL: [f32; 8] = [0.4, 30.0, 0.1, 0.5, 0.002, 0.3, 0.02, 0.0];

/// A camera at the origin looking down +z (OpenCV axes), off-centre principal point.
fn camera(w: u32, h: u32) -> Camera {
    let i4 = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let k = [
        [40.0, 0.0, w as f32 * 0.45],
        [0.0, 42.0, h as f32 * 0.55],
        [0.0, 0.0, 1.0],
    ];
    Camera::new(k, i4, w, h, 0.01, 100.0).unwrap()
}

struct Mesh {
    vertices: Vec<f32>,
    faces: Vec<i32>,
    normals: Vec<f32>,
    colors: Vec<f32>,
    materials: Vec<i32>,
}

/// Two quads: a front one at z = 2 half covering a back one at z = 3 (both facing −z).
fn two_quads() -> Mesh {
    let quad = |x0: f32, x1: f32, y0: f32, y1: f32, z: f32| vec![x0, y0, z, x1, y0, z, x1, y1, z, x0, y1, z];
    let mut vertices = quad(-0.9, 0.2, -0.7, 0.6, 2.0);
    vertices.extend(quad(-3.0, 3.0, -3.0, 3.0, 3.0));
    let faces = vec![0, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7];
    let normals = [0.0, 0.0, -1.0].repeat(8);
    let colors = [
        0.2, 0.5, 0.8, 0.2, 0.5, 0.8, 0.2, 0.5, 0.8, 0.2, 0.5, 0.8, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9, 0.9,
        0.9, 0.9, 0.9, 0.9,
    ]
    .to_vec();
    Mesh {
        vertices,
        faces,
        normals,
        colors,
        materials: vec![0; 4],
    }
}

fn inputs(m: &Mesh) -> SceneInputs<'_> {
    SceneInputs {
        vertices: &m.vertices,
        faces: &m.faces,
        normals: &m.normals,
        colors: &m.colors,
        solid: &m.vertices,
        uvs: None,
        face_material: &m.materials,
        materials: &MATERIAL,
        decals: &[],
        texture: None,
        light: LIGHT,
    }
}

fn settings(samples_per_side: u32) -> RenderSettings {
    RenderSettings {
        samples_per_side,
        edge_samples_per_side: 4,
        shadows: true,
        centre_hits: true,
        background: [1.0, 1.0, 1.0],
        seed: 3,
    }
}

fn render_on(threads: usize, m: &Mesh, s: RenderSettings) -> RenderOutput {
    on_threads(threads, || {
        let scene = Scene::new(inputs(m)).unwrap();
        render(&scene, &camera(37, 29), s).unwrap()
    })
}

#[test]
fn same_bits_for_any_thread_count() {
    let m = two_quads();
    let one = render_on(1, &m, settings(3));
    for threads in [2, 4] {
        assert!(
            one == render_on(threads, &m, settings(3)),
            "{threads} threads differ"
        );
    }
}

#[test]
fn centre_rays_see_the_nearest_quad_at_the_right_depth() {
    let m = two_quads();
    let out = render_on(2, &m, settings(1));
    let cam = camera(37, 29);
    for y in 0..29usize {
        for x in 0..37usize {
            let p = y * 37 + x;
            // Where the centre ray meets z = 2, in closed form.
            let (dx, dy) = (
                (x as f32 + 0.5 - cam.cx) / cam.fx,
                (y as f32 + 0.5 - cam.cy) / cam.fy,
            );
            let (qx, qy) = (2.0 * dx, 2.0 * dy);
            let inside_front = (-0.9..=0.2).contains(&qx) && (-0.7..=0.6).contains(&qy);
            let margin = 2e-3;
            let near_edge = [qx + 0.9, qx - 0.2, qy + 0.7, qy - 0.6]
                .iter()
                .any(|d| d.abs() < margin);
            if near_edge {
                continue;
            }
            let z = if inside_front { 2.0 } else { 3.0 };
            assert_eq!(out.centre_face[p] < 2, inside_front, "pixel ({x}, {y})");
            assert!(
                (out.depth[p] - z).abs() < 1e-5,
                "depth {} at ({x}, {y})",
                out.depth[p]
            );
            let t = z * (1.0 + dx * dx + dy * dy).sqrt();
            assert!((out.centre_t[p] - t).abs() < 1e-5 * t);
            assert_eq!(out.alpha[p], 1.0);
            // The quads face the camera: camera-space normal (0, 0, −1).
            assert!((out.normal[p * 3 + 2] + 1.0).abs() < 1e-6);
        }
    }
}

#[test]
fn missing_everything_gives_the_background() {
    let mut m = two_quads();
    m.vertices.iter_mut().skip(2).step_by(3).for_each(|z| *z = -*z); // behind the camera
    let out = render_on(2, &m, settings(2));
    assert!(out.rgb.iter().all(|&c| c == 1.0));
    assert!(out.alpha.iter().all(|&a| a == 0.0));
    assert!(out.centre_face.iter().all(|&f| f == -1));
    assert!(out.normal.iter().chain(&out.depth).all(|&v| v == 0.0));
}

#[test]
fn empty_scene_renders_background() {
    let m = Mesh {
        vertices: vec![],
        faces: vec![],
        normals: vec![],
        colors: vec![],
        materials: vec![],
    };
    let out = render_on(1, &m, settings(1));
    assert!(out.alpha.iter().all(|&a| a == 0.0));
}

#[test]
fn bad_inputs_name_the_argument() {
    let m = two_quads();
    let mut bad_faces = m.faces.clone();
    bad_faces[4] = 8;
    let err = Scene::new(SceneInputs {
        faces: &bad_faces,
        ..inputs(&m)
    })
    .err()
    .unwrap();
    assert!(matches!(err, Error::IndexOutOfRange { arg: "faces", .. }));
    let mut nan = m.vertices.clone();
    nan[5] = f32::NAN;
    let err = Scene::new(SceneInputs {
        vertices: &nan,
        ..inputs(&m)
    })
    .err()
    .unwrap();
    assert!(matches!(err, Error::NonFinite { arg: "vertices", .. }));
    let err = Scene::new(SceneInputs {
        normals: &m.normals[..9],
        ..inputs(&m)
    })
    .err()
    .unwrap();
    assert!(matches!(err, Error::Shape { arg: "normals", .. }));
    let mut materials = MATERIAL;
    materials[1] = 0.0;
    let err = Scene::new(SceneInputs {
        materials: &materials,
        ..inputs(&m)
    })
    .err()
    .unwrap();
    assert!(matches!(err, Error::Invalid { arg: "materials", .. }));
    let textured = [0.4, 30.0, 0.1, 0.0, 0.0, 0.0, 0.0, 1.0];
    let err = Scene::new(SceneInputs {
        materials: &textured,
        ..inputs(&m)
    })
    .err()
    .unwrap();
    assert!(matches!(err, Error::Invalid { arg: "uvs", .. }));
    let err = Scene::new(SceneInputs {
        light: Light {
            direction: [0.0, 0.0, 2.0],
            ..LIGHT
        },
        ..inputs(&m)
    })
    .err()
    .unwrap();
    assert!(matches!(err, Error::Invalid { arg: "light", .. }));
    let scene = Scene::new(inputs(&m)).unwrap();
    let err = render(&scene, &camera(8, 8), settings(0)).unwrap_err();
    assert!(matches!(
        err,
        Error::Invalid {
            arg: "samples_per_side",
            ..
        }
    ));
}

/// `n` random triangles in front of `camera(37, 29)`, with per-vertex normals.
fn soup(seed: u64, n: usize) -> Mesh {
    let mut rng = urhead_core::testing::Rng::new(seed);
    let mut vertices = Vec::new();
    for _ in 0..n {
        let c = [
            rng.uniform(-0.8, 0.8),
            rng.uniform(-0.7, 0.7),
            rng.uniform(1.5, 3.0),
        ];
        for _ in 0..3 {
            vertices.extend(c.map(|x| (x + rng.uniform(-0.25, 0.25)) as f32));
        }
    }
    let normals = (0..n * 3).flat_map(|_| [0.0, 0.0, -1.0]).collect();
    Mesh {
        faces: (0..3 * n as i32).collect(),
        colors: vec![0.6; n * 9],
        materials: vec![0; n],
        normals,
        vertices,
    }
}

#[test]
fn a_refit_tree_renders_what_a_fresh_tree_renders() {
    let m = soup(5, 300);
    let cam = camera(37, 29);
    let fresh = render(&Scene::new(inputs(&m)).unwrap(), &cam, settings(2)).unwrap();
    // A tree built over an unrelated soup of the same size, then refit twice: the render
    // depends only on the current triangles (random soups have no exactly tied hits).
    let mut bvh = TriangleBvh::from_mesh(&soup(6, 300).vertices, &m.faces).unwrap();
    let other = soup(7, 300);
    render(
        &Scene::with_bvh(inputs(&other), &mut bvh).unwrap(),
        &cam,
        settings(2),
    )
    .unwrap();
    let refit = render(&Scene::with_bvh(inputs(&m), &mut bvh).unwrap(), &cam, settings(2)).unwrap();
    assert!(fresh.alpha.iter().any(|&a| a > 0.0) && fresh.alpha.contains(&0.0));
    assert!(fresh == refit);
}

#[test]
fn a_tree_for_another_triangle_count_is_refused() {
    let m = soup(5, 30);
    let mut bvh = TriangleBvh::from_mesh(&m.vertices, &m.faces[..87]).unwrap();
    let err = Scene::with_bvh(inputs(&m), &mut bvh).err().unwrap();
    assert!(matches!(err, Error::Invalid { arg: "bvh", .. }), "{err}");
    let err = TriangleBvh::from_mesh(&m.vertices, &[0, 1, 90]).unwrap_err();
    assert!(
        matches!(err, Error::IndexOutOfRange { arg: "faces", .. }),
        "{err}"
    );
}
