"""urhead.data.synth.raytrace against a brute-force float64 reference on tiny scenes, its camera
convention, shading properties and determinism."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from urhead import Camera
from urhead.data.synth.raytrace import Light, Material, TriangleBvh, decal, raytrace
from urhead.errors import IndexRangeError, InvalidArgumentError, NonFiniteError


def off_centre_camera(w=48, h=40) -> Camera:
    cam = Camera.look_at((0.05, 0.1, 1.0), (0.0, 0.0, 0.0), width=w, height=h, fov_y_degrees=40)
    k = torch.tensor([[60.0, 0, 0.42 * w], [0, 64.0, 0.57 * h], [0, 0, 1]])
    return Camera(k, cam.viewmat, w, h)


def triangle_soup(rng, n=40):
    centres = rng.uniform(-0.35, 0.35, size=(n, 1, 3))
    verts = (centres + rng.normal(scale=0.12, size=(n, 3, 3))).reshape(-1, 3)
    faces = np.arange(3 * n).reshape(n, 3)
    normals = rng.normal(size=(3 * n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return verts, faces, normals


def reference_centre_rays(verts, faces, camera: Camera):
    """Brute force, float64: every pixel-centre ray against every triangle
    (Möller–Trumbore). Returns (face, t, u, v, second-best t) per pixel."""
    h, w = camera.height, camera.width
    K = camera.K.double().numpy()
    V = camera.viewmat.double().numpy()
    R, tr = V[:3, :3], V[:3, 3]
    eye = -R.T @ tr
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    d_cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    d = d_cam @ R  # camera → world (rows of R are camera axes)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    p = verts[faces].astype(np.float64)  # (F, 3, 3)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    dd = d.reshape(-1, 1, 3)
    pvec = np.cross(dd, e2[None])
    det = (e1[None] * pvec).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1 / det
        tvec = eye[None, None] - p[None, :, 0]
        u = (tvec * pvec).sum(-1) * inv
        qvec = np.cross(tvec, e1[None])
        v = (dd * qvec).sum(-1) * inv
        t = (e2[None] * qvec).sum(-1) * inv
    ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    t = np.where(ok, t, np.inf)
    order = np.argsort(t, axis=1)
    best = order[:, 0]
    rows = np.arange(len(best))
    t_sorted = np.take_along_axis(t, order[:, :2], 1)
    face = np.where(np.isfinite(t_sorted[:, 0]), best, -1)
    return (
        face.reshape(h, w),
        t_sorted[:, 0].reshape(h, w),
        u[rows, best].reshape(h, w),
        v[rows, best].reshape(h, w),
        t_sorted[:, 1].reshape(h, w),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_centre_hits_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    verts, faces, normals = triangle_soup(rng)
    camera = off_centre_camera()
    out = raytrace(verts, faces, camera, normals=normals, samples_per_side=1, shadows=False)
    face, t, u, v, t2 = reference_centre_rays(verts, faces, camera)
    # Skip pixels whose answer is ill-posed in float32: near-ties in depth, rays grazing
    # an edge (a barycentric within 1e-4 of the boundary).
    hit = face >= 0
    edge = hit & (np.minimum(np.minimum(u, v), 1 - u - v) < 1e-4)
    with np.errstate(invalid="ignore"):  # inf − inf where nothing is hit
        tie = hit & (t2 - t < 1e-5)
    clear = ~(edge | tie)
    assert clear.sum() > 0.8 * clear.size
    assert np.array_equal(out.face[clear], face[clear])
    both = clear & hit
    assert hit.sum() > 200
    # Float32 Möller–Trumbore on random (some near-grazing) triangles; worst seen over
    # these seeds: t 3.7e-6 relative, barycentrics 1.8e-5.
    np.testing.assert_allclose(out.t[both], t[both], rtol=5e-6)
    np.testing.assert_allclose(out.bary[both][:, 0], u[both], atol=2.5e-5)
    np.testing.assert_allclose(out.bary[both][:, 1], v[both], atol=2.5e-5)
    # Depth is the camera z of the hit; the normal the interpolated shading normal, in
    # camera axes, flipped towards the camera.
    R = camera.viewmat.double().numpy()[:3, :3]
    f = face[both]
    w = np.stack([1 - u[both] - v[both], u[both], v[both]], -1)
    n = (normals[faces[f]] * w[..., None]).sum(1)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    n_cam = n @ R.T
    ys, xs = np.nonzero(both)
    K = camera.K.double().numpy()
    d_cam = np.stack(
        [(xs + 0.5 - K[0, 2]) / K[0, 0], (ys + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(xs))], -1
    )
    d_cam /= np.linalg.norm(d_cam, axis=-1, keepdims=True)
    n_cam = np.where(((n_cam * d_cam).sum(-1) > 0)[:, None], -n_cam, n_cam)
    np.testing.assert_allclose(out.normal[both], n_cam, atol=4e-5)  # worst seen 2.6e-5
    np.testing.assert_allclose(out.depth[both], t[both] * d_cam[:, 2], rtol=5e-6)
    assert (out.alpha[hit & clear] == 1).all() and (out.alpha[~hit & clear] == 0).all()


def test_a_vertex_projects_where_the_tracer_sees_it():
    """A tiny triangle around a world point covers exactly the pixel that
    Camera.project gives for that point (off-centre principal point included)."""
    camera = off_centre_camera()
    rng = np.random.default_rng(5)
    tested = 0
    for _ in range(200):
        point = rng.uniform(-0.2, 0.2, size=3)
        (px, py), _ = camera.project(torch.tensor(point))
        col, row = int(px), int(py)
        # Keep the point inside its pixel so a triangle of at most ±0.38 px stays in it;
        # 10 × 10 strata of 0.1 px guarantee a sample inside the triangle.
        if min(px % 1, py % 1) < 0.4 or max(px % 1, py % 1) > 0.6:
            continue
        R = camera.viewmat.double().numpy()[:3, :3]
        right, down = R[0], R[1]
        size = 0.3 / camera.fx  # 0.3 px at 1 m; the points are 0.8–1.25 m away
        tri = np.stack([point - size * right, point + size * right, point + size * down])
        out = raytrace(tri, [[0, 1, 2]], camera, samples_per_side=10, shadows=False)
        covered = np.argwhere(out.alpha > 0)
        assert covered.tolist() == [[row, col]]
        tested += 1
    assert tested >= 5


def test_shading_depends_on_view_through_the_specular_lobe():
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]])
    faces = [[0, 1, 2], [0, 2, 3]]
    light = Light(direction=(0, 0, 1), angular_radius=0.0)
    shiny = [Material(specular=1.0, shininess=80)]
    kwargs = dict(materials=shiny, light=light, samples_per_side=1, shadows=False)
    head_on = Camera.look_at((0, 0, 2), (0, 0, 0), width=9, height=9)
    oblique = Camera.look_at((1.4, 0, 1.4), (0, 0, 0), width=9, height=9)
    a = raytrace(quad, faces, head_on, **kwargs).rgb[4, 4]
    b = raytrace(quad, faces, oblique, **kwargs).rgb[4, 4]
    matte = raytrace(quad, faces, oblique, light=light, samples_per_side=1).rgb[4, 4]
    assert (a > b + 0.5).all()  # the highlight is seen head-on only
    amb = (np.array(light.ambient_up) + np.array(light.ambient_down)) / 2
    np.testing.assert_allclose(matte, 0.8 * (1 + amb), rtol=1e-5)  # Lambert + ambient


def test_shadows_and_decals():
    # A floor lit at 45° with a small blocker 0.5 above it: the blocker's shadow falls
    # 0.5 towards −x, where the camera above sees the floor.
    floor = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1.0]])
    blocker = floor * 0.2 + np.array([0, 0.5, 0])
    verts = np.concatenate([floor, blocker])
    faces = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]
    cam = Camera.look_at((0, 3, 0.01), (0, 0, 0), up=(0, 0, -1), width=31, height=31)
    light = Light(direction=(1, 1, 0), angular_radius=0.0)
    kwargs = dict(light=light, samples_per_side=1)
    out = raytrace(verts, faces, cam, **kwargs)
    no_shadows = raytrace(verts, faces, cam, shadows=False, **kwargs)

    def pixel(point):
        (px, py), _ = cam.project(torch.tensor(point, dtype=torch.float64))
        return int(py), int(px)

    shadowed, lit = pixel([-0.5, 0.0, 0.0]), pixel([0.5, 0.0, 0.0])
    assert out.face[shadowed] in (0, 1) and out.face[lit] in (0, 1)
    diffuse = 0.8 * np.sqrt(0.5)  # albedo · n·l
    np.testing.assert_allclose(no_shadows.rgb[shadowed] - out.rgb[shadowed], diffuse, rtol=1e-5)
    assert np.array_equal(out.rgb[lit], no_shadows.rgb[lit])
    spot = decal((0.3, 0, 0.3), radius=0.1, color=(1, 0, 0))
    painted = raytrace(verts, faces, cam, decals=np.array([spot]), **kwargs)
    r, c = pixel([0.3, 0.0, 0.3])
    assert painted.rgb[r, c, 0] > 0.9 and painted.rgb[r, c, 1] < 0.3
    assert np.array_equal(painted.rgb[lit], out.rgb[lit])


def test_a_kept_tree_refit_to_each_frame_renders_like_a_fresh_one():
    """The frames of an animation traced with one TriangleBvh (built over another shape)
    give the same bits as building a tree per frame."""
    rng = np.random.default_rng(7)
    verts, faces, normals = triangle_soup(rng, 60)
    tree = TriangleBvh(triangle_soup(rng, 60)[0], faces)
    assert tree.num_faces == 60
    cam = off_centre_camera()
    for step in range(3):
        frame = verts + step * np.array([0.05, -0.02, 0.03])
        kwargs = dict(normals=normals, samples_per_side=2, edge_samples_per_side=3, seed=step)
        fresh = raytrace(frame, faces, cam, **kwargs)
        kept = raytrace(frame, faces, cam, bvh=tree, **kwargs)
        assert (fresh.face >= 0).any()
        for a, b in zip(fresh, kept, strict=True):
            assert np.array_equal(a, b)


def test_without_centre_hits_the_image_is_the_same():
    verts, faces, normals = triangle_soup(np.random.default_rng(8), 40)
    kwargs = dict(normals=normals, samples_per_side=2, edge_samples_per_side=3)
    full = raytrace(verts, faces, off_centre_camera(), **kwargs)
    image = raytrace(verts, faces, off_centre_camera(), centre_hits=False, **kwargs)
    assert image.face is None and image.bary is None and image.t is None
    for a, b in zip(full[:4], image[:4], strict=True):
        assert np.array_equal(a, b)


def test_bad_inputs_are_typed_and_named():
    verts = np.zeros((3, 3))
    cam = Camera.look_at((0, 0, 1), (0, 0, 0), width=8, height=8)
    with pytest.raises(IndexRangeError, match="faces"):
        raytrace(verts, [[0, 1, 3]], cam)
    with pytest.raises(NonFiniteError, match="vertices"):
        raytrace(np.full((3, 3), np.nan), [[0, 1, 2]], cam, normals=np.ones((3, 3)))
    with pytest.raises(InvalidArgumentError, match="samples_per_side"):
        raytrace(verts, [[0, 1, 2]], cam, samples_per_side=0)
    with pytest.raises(IndexRangeError, match="face_material"):
        raytrace(verts, [[0, 1, 2]], cam, face_material=[1])
    with pytest.raises(InvalidArgumentError, match="uvs"):
        raytrace(verts, [[0, 1, 2]], cam, materials=[Material(textured=True)])
    tree = TriangleBvh(verts, [[0, 1, 2]])
    with pytest.raises(InvalidArgumentError, match="bvh was built over 1 faces"):
        raytrace(np.zeros((4, 3)), [[0, 1, 2], [1, 2, 3]], cam, bvh=tree)
    with pytest.raises(IndexRangeError, match="faces"):
        TriangleBvh(verts, [[0, 1, 3]])
    with pytest.raises(NonFiniteError, match="vertices"):
        TriangleBvh(np.full((3, 3), np.inf), [[0, 1, 2]])


def test_same_bits_for_1_2_and_4_threads():
    """A separate process per thread count: URHEAD_NUM_THREADS is read per call."""
    code = (
        "import numpy as np, sys\n"
        "from test_data_raytrace import triangle_soup, off_centre_camera\n"
        "from urhead.data.synth.raytrace import raytrace, Material\n"
        "v, f, n = triangle_soup(np.random.default_rng(4))\n"
        "m = Material(specular=0.5, pore_strength=0.5, pore_size=0.01, mottle_strength=0.3)\n"
        "o = raytrace(v, f, off_centre_camera(), normals=n, materials=[m], samples_per_side=2,"
        " edge_samples_per_side=4)\n"
        "sys.stdout.buffer.write(b''.join(a.tobytes() for a in o))\n"
    )
    here = os.path.dirname(__file__)
    outputs = []
    for threads in ("1", "2", "4"):
        env = {**os.environ, "URHEAD_NUM_THREADS": threads, "PYTHONPATH": here}
        run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, check=True)
        outputs.append(run.stdout)
    assert len(outputs[0]) > 0 and outputs[0] == outputs[1] == outputs[2]
