"""End-to-end sanity optimisation through the whole mesh chain, in the spirit of
nvdiffrast's pose and texture samples: recover an object's rotation, first from
silhouettes alone (the antialiasing gradient), then jointly with its texture, from four
64 × 64 renders."""

import math

import pytest
import torch

import urhead
from raster_meshes import uv_sphere
from urhead import ops
from urhead.ops._reference import axis_angle_to_matrix

BACKGROUND = torch.tensor([0.2, 0.3, 0.4])


@pytest.fixture
def one_torch_thread():
    # Hundreds of tiny torch ops alternate with urhead kernels here; torch's OpenMP workers
    # spin-wait between ops and starve urhead's pool on a 2-core machine. One torch thread
    # (and so one urhead thread, which follows it) keeps the test at a few seconds.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def posed(verts, rotation):
    return verts @ axis_angle_to_matrix(rotation).T


def render(scene, tex, rotation, cam):
    verts, faces, uvs, uv_faces, topology = scene
    p = posed(verts, rotation)
    raster = ops.rasterize(p, faces, cam)
    uv = ops.interpolate(uvs, raster, uv_faces)
    color = torch.where((raster.tri_id >= 0)[..., None], ops.texture(tex, uv), BACKGROUND)
    return ops.antialias(color, raster, p, faces, cam, topology)


def silhouette(scene, rotation, cam):
    verts, faces, _, _, topology = scene
    p = posed(verts, rotation)
    raster = ops.rasterize(p, faces, cam)
    mask = (raster.tri_id >= 0)[..., None].to(verts.dtype)
    return ops.antialias(mask, raster, p, faces, cam, topology)


def rotation_error_degrees(a, b):
    r = axis_angle_to_matrix(a) @ axis_angle_to_matrix(b).T
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(r.trace()) - 1) / 2))))


def test_recovers_rotation_and_texture_from_four_views(one_torch_thread):
    torch.manual_seed(0)
    verts, faces, uvs, uv_faces = uv_sphere(12, 16, dtype=torch.float32)
    verts = verts * torch.tensor([1.0, 0.75, 0.55])  # an ellipsoid, so the pose shows
    scene = (verts, faces, uvs, uv_faces, ops.antialias_topology(faces, verts.shape[0]))
    cams = [
        urhead.Camera.look_at(eye, (0, 0, 0), (0, -1, 0), fov_y_degrees=40, width=64, height=64)
        for eye in [(0, 0, -3.2), (3.2, 0.5, 0), (-2.2, 1.5, 2.2), (0.5, -3.0, 1.0)]
    ]
    coarse = torch.rand(1, 3, 4, 6)
    true_tex = torch.nn.functional.interpolate(coarse, size=(16, 24), mode="bilinear")[0]
    true_tex = true_tex.permute(1, 2, 0).contiguous()
    true_rot = torch.tensor([0.3, -0.5, 0.2])
    with torch.no_grad():
        images = [render(scene, true_tex, true_rot, c) for c in cams]
        masks = [silhouette(scene, true_rot, c) for c in cams]
    rot = (true_rot + torch.tensor([0.25, 0.3, -0.2])).requires_grad_(True)
    assert rotation_error_degrees(rot.detach(), true_rot) > 20

    # 1. Pose from silhouettes: only antialiasing gives coverage a gradient.
    opt = torch.optim.Adam([rot], lr=0.02)
    for _ in range(60):
        opt.zero_grad()
        sum(
            (silhouette(scene, rot, c) - m).square().mean()
            for c, m in zip(cams, masks, strict=True)
        ).backward()
        opt.step()
    assert rotation_error_degrees(rot.detach(), true_rot) < 1.0

    # 2. Pose and texture jointly; the texture gradient is sparse (SparseAdam).
    tex = torch.nn.Parameter(torch.full((16, 24, 3), 0.5))
    opt_rot = torch.optim.Adam([rot], lr=0.005)
    opt_tex = torch.optim.SparseAdam([tex], lr=0.05)
    losses = []
    for _ in range(80):
        opt_rot.zero_grad()
        opt_tex.zero_grad()
        loss = sum(
            (render(scene, tex, rot, c) - t).square().mean()
            for c, t in zip(cams, images, strict=True)
        )
        loss.backward()
        opt_rot.step()
        opt_tex.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.01 * losses[0]
    assert rotation_error_degrees(rot.detach(), true_rot) < 0.5
    seen = tex.detach() != 0.5
    assert seen.float().mean() > 0.5
    assert (tex.detach() - true_tex)[seen].abs().mean() < 0.02
