"""urhead.ops.interpolate against the reference and finite differences."""

import pytest
import torch

from raster_meshes import camera, uv_sphere
from urhead import ops
from urhead.ops import _reference as ref


def rel_err(a, b):
    return float((a - b).norm() / b.norm())


@pytest.fixture(scope="module")
def scene():
    verts, faces, uvs, uv_faces = uv_sphere(10, 14, jitter=0.04, seed=7)
    return verts, faces, uvs, uv_faces, camera(eye=(0.8, 0.5, -2.7))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_matches_reference(scene, dtype):
    verts, faces, uvs, uv_faces, cam = scene
    raster = ops.rasterize(verts.to(dtype), faces, cam)
    attr = torch.randn(verts.shape[0], 5, dtype=dtype, generator=torch.Generator().manual_seed(0))
    out = ops.interpolate(attr, raster, faces)
    assert out.shape == (cam.height, cam.width, 5) and out.dtype == dtype
    expected = ref.interpolate(attr.double(), raster._replace(bary=raster.bary.double()), faces)
    assert (out.double() - expected).abs().max() < (1e-6 if dtype == torch.float32 else 1e-14)
    assert (out[raster.tri_id < 0] == 0).all()
    # UV coordinates through the UV faces (seam vertices are duplicated in UV only).
    uv = ops.interpolate(uvs.to(dtype), raster, uv_faces)
    uv_ref = ref.interpolate(uvs.double(), raster._replace(bary=raster.bary.double()), uv_faces)
    assert (uv.double() - uv_ref).abs().max() < (5e-7 if dtype == torch.float32 else 1e-14)


def test_gradients_match_reference_through_the_rasterizer(scene):
    verts, faces, _, _, cam = scene
    v = verts.clone().requires_grad_(True)
    attr = torch.randn(verts.shape[0], 3, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(cam.height, cam.width, 3, dtype=torch.float64)
    grads = torch.autograd.grad(
        (ops.interpolate(attr, ops.rasterize(v, faces, cam), faces) * weights).sum(), (attr, v)
    )
    expected = torch.autograd.grad(
        (ref.interpolate(attr, ref.rasterize(v, faces, cam), faces) * weights).sum(), (attr, v)
    )
    for g, e in zip(grads, expected, strict=True):
        assert rel_err(g, e) < 1e-12


def test_float32_gradients_agree_with_float64(scene):
    verts, faces, _, _, cam = scene
    raster = ops.rasterize(verts, faces, cam)
    attr = torch.randn(verts.shape[0], 4, dtype=torch.float64)
    weights = torch.randn(cam.height, cam.width, 4, dtype=torch.float64)

    def grads(dtype):
        a = attr.to(dtype).requires_grad_(True)
        b = raster.bary.to(dtype).requires_grad_(True)
        out = ops.interpolate(a, raster._replace(bary=b), faces)
        return torch.autograd.grad((out * weights.to(dtype)).sum(), (a, b))

    for g32, g64 in zip(grads(torch.float32), grads(torch.float64), strict=True):
        assert rel_err(g32.double(), g64) < 5e-7


def test_gradcheck_attr_and_bary(scene):
    verts, faces, _, _, _ = scene
    cam = camera(width=12, height=10)
    raster = ops.rasterize(verts, faces, cam)
    attr = torch.randn(verts.shape[0], 2, dtype=torch.float64, requires_grad=True)
    bary = raster.bary.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda a, b: ops.interpolate(a, raster._replace(bary=b), faces), (attr, bary)
    )


def test_only_requested_gradients_are_computed(scene):
    verts, faces, _, _, cam = scene
    raster = ops.rasterize(verts, faces, cam)
    attr = torch.randn(verts.shape[0], 2, dtype=torch.float64, requires_grad=True)
    out = ops.interpolate(attr, raster, faces)
    (g,) = torch.autograd.grad(out.sum(), attr)
    # Each vertex's gradient is the sum of its weights over the pixels it touches.
    total = g[:, 0].sum()
    assert abs(float(total) - float((raster.tri_id >= 0).sum())) < 1e-9
    assert torch.equal(g[:, 0], g[:, 1])
