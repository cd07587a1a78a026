"""Bad input (NUMERICS.md case 26) and determinism across thread counts (case 27) for the
mesh rasterizer ops."""

import warnings

import pytest
import torch

import urhead
from raster_meshes import camera, uv_sphere
from urhead import ops
from urhead.errors import (
    DTypeError,
    IndexRangeError,
    InvalidArgumentError,
    NonFiniteError,
    ShapeError,
)


@pytest.fixture
def mesh():
    verts, faces, uvs, uv_faces = uv_sphere(6, 8, dtype=torch.float32)
    return verts, faces, uvs, uv_faces, camera(width=24, height=20)


# --- NUMERICS.md case 26 ------------------------------------------------------------------


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_case26_non_finite_vertices(mesh, bad, stability):
    verts, faces, _, _, cam = mesh
    verts = verts.clone()
    verts[3, 1] = bad
    with pytest.raises(NonFiniteError, match="verts"):
        ops.rasterize(verts, faces, cam)
    raster = ops.rasterize(mesh[0], faces, cam)
    color = torch.zeros(cam.height, cam.width, 3)
    with pytest.raises(NonFiniteError, match="verts"):
        ops.antialias(color, raster, verts, faces, cam)
    stability.checked(26, "mesh: non-finite vertices → NonFiniteError naming verts", 2)


def test_case26_non_finite_camera(stability):
    k = torch.eye(3)
    k[0, 0] = float("nan")
    with pytest.raises(InvalidArgumentError, match="K"):
        urhead.Camera(k, torch.eye(4), 8, 8)
    view = torch.eye(4)
    view[0, 3] = float("inf")
    with pytest.raises(InvalidArgumentError, match="viewmat"):
        urhead.Camera(torch.eye(3), view, 8, 8)
    stability.checked(26, "camera: NaN in K, inf in viewmat → error naming it", 2)


def test_case26_non_finite_texels_and_attributes(mesh, stability):
    verts, faces, uvs, uv_faces, cam = mesh
    tex = torch.rand(8, 8, 3)
    tex[2, 3, 1] = float("nan")
    uv = torch.tensor([[3.5 / 8, 1 - 2.5 / 8]])  # the centre of texel (2, 3)
    with pytest.raises(NonFiniteError, match="tex"):
        ops.texture(tex, uv)
    # A non-finite texel that is never sampled is harmless (textures are not scanned).
    assert torch.isfinite(ops.texture(tex, torch.tensor([[0.9, 0.1]]))).all()
    raster = ops.rasterize(verts, faces, cam)
    attr = torch.rand(verts.shape[0], 2)
    attr[0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match="attr"):
        ops.interpolate(attr, raster, faces)
    bad_uv = uvs.clone()
    bad_uv[1, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="uv_coords"):
        ops.rasterize_uv(bad_uv, uv_faces, 8, 8)
    stability.checked(
        26, "mesh: non-finite sampled texel, attribute, UV coordinate → named error", 3
    )


def test_case26_wrong_shapes_and_dtypes(mesh, stability):
    verts, faces, _, _, cam = mesh
    with pytest.raises(ShapeError, match="verts"):
        ops.rasterize(torch.zeros(5, 4), faces, cam)
    with pytest.raises(ShapeError, match="faces"):
        ops.rasterize(verts, torch.zeros(4, 4, dtype=torch.int32), cam)
    with pytest.raises(DTypeError, match="faces"):
        ops.rasterize(verts, faces.float(), cam)
    with pytest.raises(DTypeError, match="verts"):
        ops.rasterize(verts.to(torch.int32), faces, cam)
    with pytest.raises(DTypeError, match="camera"):
        ops.rasterize(verts, faces, "camera")
    raster = ops.rasterize(verts, faces, cam)
    with pytest.raises(DTypeError, match="attr"):
        ops.interpolate(torch.zeros(verts.shape[0], 2, dtype=torch.float64), raster, faces)
    with pytest.raises(ShapeError, match="tex"):
        ops.texture(torch.zeros(4, 4), torch.zeros(3, 2))
    with pytest.raises(ShapeError, match="uv"):
        ops.texture(torch.zeros(4, 4, 1), torch.zeros(3, 3))
    with pytest.raises(DTypeError, match="uv"):
        ops.texture(torch.zeros(4, 4, 1), torch.zeros(3, 2, dtype=torch.float64))
    with pytest.raises(ShapeError, match="color"):
        ops.antialias(torch.zeros(cam.height + 1, cam.width, 3), raster, verts, faces, cam)
    with pytest.raises(ShapeError, match="topology"):
        ops.antialias(
            torch.zeros(cam.height, cam.width, 3), raster, verts, faces, cam, topology=faces[:3]
        )
    # Off the CPU, or not strided (sparse): named before any work.
    with pytest.raises(DTypeError, match="verts must be on the CPU, got device meta"):
        ops.rasterize(verts.to("meta"), faces, cam)
    with pytest.raises(DTypeError, match=r"uv must be a dense .*sparse_coo"):
        ops.texture(torch.zeros(4, 4, 1), torch.zeros(3, 2).to_sparse())
    with warnings.catch_warnings():  # torch's note that CSR support is in beta
        warnings.simplefilter("ignore", UserWarning)
        csr = torch.zeros(3, 2).to_sparse_csr()
    with pytest.raises(DTypeError, match=r"uv must be a dense .*sparse_csr"):
        ops.texture(torch.zeros(4, 4, 1), csr)
    stability.checked(26, "mesh: wrong shapes, dtypes, devices and layouts named", 14)


def test_case26_indices_out_of_range(mesh, stability):
    verts, faces, uvs, uv_faces, cam = mesh
    bad = faces.clone()
    bad[2, 1] = verts.shape[0]
    with pytest.raises(IndexRangeError, match="faces"):
        ops.rasterize(verts, bad, cam)
    bad[2, 1] = -1
    with pytest.raises(IndexRangeError, match="faces"):
        ops.rasterize(verts, bad, cam)
    with pytest.raises(IndexRangeError, match="uv_faces"):
        ops.rasterize_uv(uvs, uv_faces + uvs.shape[0], 8, 8)
    raster = ops.rasterize(verts, faces, cam)
    forged = raster._replace(tri_id=raster.tri_id + faces.shape[0])
    with pytest.raises(IndexRangeError, match="tri_id"):
        ops.interpolate(torch.zeros(verts.shape[0], 1), forged, faces)
    stability.checked(26, "mesh: faces, uv_faces, tri_id out of range → IndexRangeError", 4)


def test_case26_zero_size_empty_and_non_contiguous(mesh, stability):
    verts, faces, uvs, uv_faces, cam = mesh
    with pytest.raises(InvalidArgumentError, match="width"):
        urhead.Camera(torch.eye(3), torch.eye(4), 0, 8)
    with pytest.raises(ShapeError, match="height"):
        ops.rasterize_uv(uvs, uv_faces, 0, 8)
    with pytest.raises(ShapeError, match="faces"):
        ops.rasterize(verts, torch.zeros(0, 3, dtype=torch.int32), cam)
    with pytest.raises(ShapeError, match="verts"):
        ops.rasterize(torch.zeros(0, 3), torch.zeros(1, 3, dtype=torch.int32), cam)
    with pytest.raises(InvalidArgumentError, match="contiguous"):
        ops.rasterize(verts.t().contiguous().t(), faces, cam)
    with pytest.raises(InvalidArgumentError, match="contiguous"):
        ops.texture(torch.zeros(4, 4, 2)[:, :, :1], torch.zeros(3, 2))
    with pytest.raises(InvalidArgumentError, match="contiguous"):
        ops.texture(torch.zeros(4, 4, 1), torch.zeros(2, 3)[:, :2])
    stability.checked(26, "mesh: zero-size image, empty mesh, non-contiguous → named error", 7)


# --- NUMERICS.md case 27 ------------------------------------------------------------------


def render_chain():
    """rasterize → interpolate → texture → antialias, forward and backward; every output
    and gradient, flattened."""
    verts, faces, uvs, uv_faces = uv_sphere(16, 24, jitter=0.02, seed=5, dtype=torch.float32)
    cam = camera(width=96, height=80, eye=(0.4, 0.3, -2.6))
    v = verts.clone().requires_grad_(True)
    tex = torch.rand(64, 48, 5, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    raster = ops.rasterize(v, faces, cam)
    uv = ops.interpolate(uvs, raster, uv_faces)
    color = ops.texture(tex, uv)
    out = ops.antialias(color, raster, v, faces, cam)
    weights = torch.rand(out.shape, generator=torch.Generator().manual_seed(1))
    (out * weights).sum().backward()
    grads = [v.grad, tex.grad._indices(), tex.grad._values()]
    return [raster.tri_id, raster.bary, raster.depth, uv, color, out, *grads]


def test_case27_bitwise_identical_across_thread_counts_and_runs(monkeypatch, stability):
    monkeypatch.setenv("URHEAD_NUM_THREADS", "1")
    reference = render_chain()
    assert (reference[0] >= 0).sum() > 1000
    for threads in ("1", "2", "4"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        for _ in range(10 if threads == "4" else 3):
            for a, b in zip(render_chain(), reference, strict=True):
                differing = (a != b).sum() if a.shape == b.shape else a.numel() + b.numel()
                stability.record(
                    27, "mesh chain: elements differing from the 1-thread run", differing, 0
                )
                assert torch.equal(a, b)
