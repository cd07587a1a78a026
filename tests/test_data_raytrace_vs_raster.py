"""The ray tracer (ground truth) and the training rasterizer share no code; on a plain
mesh they must agree on visibility, barycentrics, depth and shaded colour: proof that the
camera, pixel-centre and barycentric conventions match."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from urhead import Camera
from urhead.data.synth.raytrace import Light, Material, raytrace
from urhead.head import procedural_head
from urhead.head.mesh import vertex_normals_numpy
from urhead.ops import interpolate, rasterize


@pytest.fixture(scope="module")
def head_scene():
    head = procedural_head(0)
    out = head.skin(pose=torch.tensor([0.1, 0.5, 0.05, 0, 0, 0, 0.2, 0, 0, 0, 0, 0, 0, 0, 0]))
    verts = out.verts[0].numpy()
    cam = Camera.look_at(
        (0.05, 0.02, 0.6), (0.0, -0.01, 0.0), fov_y_degrees=30, width=96, height=80
    )
    k = cam.K.clone()
    k[0, 2] += 3.3  # off-centre principal point
    k[1, 2] -= 2.1
    camera = Camera(k, cam.viewmat, 96, 80)
    rng = np.random.default_rng(0)
    colors = rng.uniform(0.2, 0.9, size=(head.num_vertices, 3)).astype(np.float32)
    return verts, np.array(head.faces), colors, camera


def test_visibility_barycentrics_and_depth_agree(head_scene):
    verts, faces, _, camera = head_scene
    traced = raytrace(verts, faces, camera, samples_per_side=1, shadows=False)
    raster = rasterize(torch.from_numpy(verts), torch.from_numpy(faces), camera)
    tri = raster.tri_id.numpy()
    hit = traced.face >= 0
    assert hit.mean() > 0.3
    assert np.array_equal(hit, tri >= 0)
    same = hit & (traced.face == tri)
    # Different faces only where the centre ray passes within 1e-3 (barycentric) of an edge
    # or two surfaces lie within 1e-4 in depth (the rasterizer snaps vertices to 1/256 px,
    # which moves grazing surfaces by up to ~5e-5 in depth here): both are right there.
    u, v = traced.bary[..., 0], traced.bary[..., 1]
    near_edge = np.minimum(np.minimum(u, v), 1 - u - v) < 1e-3
    differ = hit & (tri >= 0) & ~same
    assert differ.sum() <= 0.01 * hit.sum()
    assert (near_edge[differ] | (np.abs(traced.depth - raster.depth.numpy())[differ] < 1e-4)).all()
    # Worst seen: barycentrics 3.2e-4 (snapping), depth 3.9e-6 relative.
    np.testing.assert_allclose(raster.bary.numpy()[same], traced.bary[same], atol=5e-4)
    np.testing.assert_allclose(raster.depth.numpy()[same], traced.depth[same], rtol=1e-5)


def test_shaded_colour_agrees(head_scene):
    """Lambert + hemisphere ambient from interpolated colours and normals, computed on the
    rasterizer's interpolate output, equals the ray tracer's image."""
    verts, faces, colors, camera = head_scene
    light = Light(direction=(0.3, 0.5, 0.8), angular_radius=0.0)
    matte = [Material(specular=0.0, wrap=0.0)]
    normals = vertex_normals_numpy(verts, faces)
    traced = raytrace(
        verts,
        faces,
        camera,
        normals=normals,
        colors=colors,
        materials=matte,
        light=light,
        samples_per_side=1,
        shadows=False,
        background=(0, 0, 0),
    )
    f = torch.from_numpy(faces)
    raster = rasterize(torch.from_numpy(verts), f, camera)
    albedo = interpolate(torch.from_numpy(colors), raster, f)
    n = interpolate(torch.from_numpy(normals), raster, f)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # Flip normals that face away from the viewer, as the tracer shades both sides.
    ys, xs = torch.meshgrid(torch.arange(80) + 0.5, torch.arange(96) + 0.5, indexing="ij")
    d_cam = torch.stack(
        [(xs - camera.cx) / camera.fx, (ys - camera.cy) / camera.fy, torch.ones_like(xs)], -1
    )
    d_world = d_cam @ camera.viewmat[:3, :3]
    n = torch.where(((n * d_world).sum(-1) > 0)[..., None], -n, n)
    direction, color, _, up, down, world_up = light.core_args()
    l_dir = torch.tensor(direction)
    sky = 0.5 + 0.5 * (n @ torch.tensor(world_up))
    ambient = torch.tensor(down) + (torch.tensor(up) - torch.tensor(down)) * sky[..., None]
    shade = albedo * (torch.tensor(color) * (n @ l_dir).clamp_min(0)[..., None] + ambient)
    same = (traced.face >= 0) & (traced.face == raster.tri_id.numpy())
    error = np.abs(shade.numpy()[same] - traced.rgb[same])
    assert same.sum() > 1000
    assert error.max() < 2e-4  # worst seen 1.4e-4 (barycentric snapping in the rasterizer)
