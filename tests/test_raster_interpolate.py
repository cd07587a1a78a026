"""urhead.ops.interpolate against the reference and finite differences."""

import pytest
import torch

from raster_meshes import camera, uv_sphere
from urhead import ops
from urhead.errors import DTypeError, IndexRangeError, InvalidArgumentError, ShapeError
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


# --- At a list of pixels -------------------------------------------------------------------


def covered_pixels(raster):
    return (raster.tri_id.reshape(-1) >= 0).nonzero()[:, 0]


def random_pixels(cam, n, seed):
    """Any order, repeats, empty pixels."""
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, cam.height * cam.width, (n,), generator=g)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pixels_give_the_image_values_bit_for_bit(scene, dtype):
    verts, faces, uvs, uv_faces, cam = scene
    raster = ops.rasterize(verts.to(dtype), faces, cam)
    attr = torch.randn(verts.shape[0], 5, dtype=dtype, generator=torch.Generator().manual_seed(0))
    pixels = random_pixels(cam, 1500, seed=1)
    out = ops.interpolate(attr, raster, faces, pixels)
    assert out.shape == (1500, 5) and out.dtype == dtype
    assert torch.equal(out, ops.interpolate(attr, raster, faces).reshape(-1, 5)[pixels])
    empty = raster.tri_id.reshape(-1)[pixels] < 0
    assert empty.any() and (out[empty] == 0).all()
    expected = ref.interpolate(
        attr.double(), raster._replace(bary=raster.bary.double()), faces, pixels
    )
    assert (out.double() - expected).abs().max() < (1e-6 if dtype == torch.float32 else 1e-14)
    uv = ops.interpolate(uvs.to(dtype), raster, uv_faces, covered_pixels(raster))
    assert torch.equal(uv, ops.interpolate(uvs.to(dtype), raster, uv_faces)[raster.tri_id >= 0])


def test_pixel_gradients_match_reference_through_the_rasterizer(scene):
    verts, faces, _, _, cam = scene
    v = verts.clone().requires_grad_(True)
    attr = torch.randn(verts.shape[0], 3, dtype=torch.float64, requires_grad=True)
    pixels = random_pixels(cam, 2500, seed=2)
    weights = torch.randn(pixels.shape[0], 3, dtype=torch.float64)
    grads = torch.autograd.grad(
        (ops.interpolate(attr, ops.rasterize(v, faces, cam), faces, pixels) * weights).sum(),
        (attr, v),
    )
    expected = torch.autograd.grad(
        (ref.interpolate(attr, ref.rasterize(v, faces, cam), faces, pixels) * weights).sum(),
        (attr, v),
    )
    for g, e in zip(grads, expected, strict=True):
        assert rel_err(g, e) < 1e-12


def test_covered_pixels_in_order_give_the_image_gradients_bit_for_bit(scene):
    """What ``Avatar.shade_mesh`` relies on: the same gradients as indexing the image."""
    verts, faces, _, _, cam = scene
    raster = ops.rasterize(verts.float(), faces, cam)
    pixels = covered_pixels(raster)
    weights = torch.randn(pixels.shape[0], 4, generator=torch.Generator().manual_seed(3))

    def grads(listed):
        attr = torch.randn(verts.shape[0], 4, generator=torch.Generator().manual_seed(4))
        attr.requires_grad_(True)
        bary = raster.bary.clone().requires_grad_(True)
        r = raster._replace(bary=bary)
        if listed:
            out = ops.interpolate(attr, r, faces, pixels)
        else:
            out = ops.interpolate(attr, r, faces).reshape(-1, 4)[pixels]
        return torch.autograd.grad((out * weights).sum(), (attr, bary))

    for g, e in zip(grads(True), grads(False), strict=True):
        assert torch.equal(g, e)


def test_repeated_pixels_sum_their_gradients(scene):
    verts, faces, _, _, cam = scene
    raster = ops.rasterize(verts, faces, cam)
    pixel = int(covered_pixels(raster)[10])
    attr = torch.randn(verts.shape[0], 2, dtype=torch.float64, requires_grad=True)
    bary = raster.bary.clone().requires_grad_(True)
    out = ops.interpolate(attr, raster._replace(bary=bary), faces, torch.tensor([pixel] * 3))
    g_attr, g_bary = torch.autograd.grad(out.sum(), (attr, bary))
    once = ops.interpolate(attr, raster._replace(bary=bary), faces, torch.tensor([pixel]))
    e_attr, e_bary = torch.autograd.grad(once.sum(), (attr, bary))
    assert torch.allclose(g_attr, 3 * e_attr, rtol=1e-14, atol=0)
    assert torch.allclose(g_bary, 3 * e_bary, rtol=1e-14, atol=0)
    assert (g_bary.reshape(-1, 2)[pixel] != 0).all()
    assert g_bary.count_nonzero() == 2


def test_gradcheck_with_pixels(scene):
    verts, faces, _, _, _ = scene
    cam = camera(width=12, height=10)
    raster = ops.rasterize(verts, faces, cam)
    attr = torch.randn(verts.shape[0], 2, dtype=torch.float64, requires_grad=True)
    bary = raster.bary.clone().requires_grad_(True)
    pixels = torch.cat([covered_pixels(raster).flip(0), torch.tensor([0, 7, 7, 119])])
    assert torch.autograd.gradcheck(
        lambda a, b: ops.interpolate(a, raster._replace(bary=b), faces, pixels), (attr, bary)
    )


@pytest.mark.parametrize("increasing", [False, True])
def test_pixels_are_bitwise_identical_across_thread_counts(
    scene, monkeypatch, increasing, stability
):
    verts, faces, _, _, cam = scene
    pixels = random_pixels(cam, 3000, seed=5)
    if increasing:
        pixels = pixels.sort().values
    weights = torch.randn(3000, 3, generator=torch.Generator().manual_seed(6))

    def run():
        v = verts.float().requires_grad_(True)
        attr = torch.randn(verts.shape[0], 3, generator=torch.Generator().manual_seed(7))
        attr.requires_grad_(True)
        out = ops.interpolate(attr, ops.rasterize(v, faces, cam), faces, pixels)
        return [out, *torch.autograd.grad((out * weights).sum(), (attr, v))]

    monkeypatch.setenv("URHEAD_NUM_THREADS", "1")
    reference = run()
    for threads in ("2", "3"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        for a, b in zip(run(), reference, strict=True):
            assert torch.equal(a, b)
    stability.checked(27, "interpolate at listed pixels: 1, 2, 3 threads, values and gradients", 3)


def test_an_empty_pixel_list(scene):
    verts, faces, _, _, cam = scene
    raster = ops.rasterize(verts, faces, cam)
    attr = torch.randn(verts.shape[0], 3, dtype=torch.float64, requires_grad=True)
    bary = raster.bary.clone().requires_grad_(True)
    out = ops.interpolate(attr, raster._replace(bary=bary), faces, torch.zeros(0, dtype=torch.long))
    assert out.shape == (0, 3)
    g_attr, g_bary = torch.autograd.grad(out.sum(), (attr, bary))
    assert not g_attr.any() and not g_bary.any() and g_bary.shape == bary.shape


def test_bad_pixels_are_refused_naming_them(scene, stability):
    verts, faces, _, _, cam = scene
    raster = ops.rasterize(verts, faces, cam)
    attr = torch.zeros(verts.shape[0], 2, dtype=torch.float64)
    n = cam.height * cam.width
    for bad in (n, -1):
        with pytest.raises(IndexRangeError, match="pixels"):
            ops.interpolate(attr, raster, faces, torch.tensor([0, bad]))
    for wrong_dtype in (torch.int32, torch.float64):
        with pytest.raises(DTypeError, match="pixels"):
            ops.interpolate(attr, raster, faces, torch.tensor([0, 1], dtype=wrong_dtype))
    with pytest.raises(DTypeError, match="pixels"):
        ops.interpolate(attr, raster, faces, [0, 1])
    with pytest.raises(ShapeError, match="pixels"):
        ops.interpolate(attr, raster, faces, torch.tensor([[0, 1]]))
    with pytest.raises(InvalidArgumentError, match="pixels"):
        ops.interpolate(attr, raster, faces, torch.arange(6)[::2])
    stability.checked(26, "interpolate: pixels out of range, of another dtype or shape named", 7)
