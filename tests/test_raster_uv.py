"""urhead.ops.rasterize_uv against the reference, texel-centre consistency, and the
watertight UV grid of NUMERICS.md case 4."""

import pytest
import torch

from raster_meshes import grid, uv_sphere
from urhead import ops
from urhead.ops import _reference as ref


@pytest.mark.parametrize("size", [(48, 64), (17, 23)])
def test_matches_reference(size):
    _, _, uvs, uv_faces = uv_sphere(9, 13)
    g = torch.Generator().manual_seed(0)
    uvs = (uvs + 0.01 * torch.randn(uvs.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    out = ops.rasterize_uv(uvs, uv_faces, *size)
    expected = ref.rasterize_uv(uvs, uv_faces, *size)
    assert torch.equal(out.tri_id, expected.tri_id)
    assert (out.tri_id >= 0).float().mean() > 0.9
    assert (out.bary - expected.bary).abs().max() < 1e-12


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_barycentrics_reconstruct_the_texel_centres(dtype):
    _, _, uvs, uv_faces = uv_sphere(9, 13, dtype=dtype)
    h, w = 40, 56
    out = ops.rasterize_uv(uvs, uv_faces, h, w)
    uv = ops.interpolate(uvs, out, uv_faces)
    r, c = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    centres = torch.stack([(c + 0.5) / w, 1 - (r + 0.5) / h], -1)
    covered = out.tri_id >= 0
    assert covered.all()  # the lat-long layout tiles the unit square
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    assert (uv.double() - centres)[covered].abs().max() < tol


def test_overlapping_islands_resolve_to_the_lower_triangle_id():
    uvs = torch.tensor([[0.1, 0.1], [0.9, 0.1], [0.5, 0.9], [0.2, 0.2], [0.8, 0.3], [0.5, 0.95]])
    faces = torch.tensor([[3, 4, 5], [0, 1, 2]], dtype=torch.int32)
    both = ops.rasterize_uv(uvs, faces, 32, 32).tri_id
    alone1 = ops.rasterize_uv(uvs, faces[1:], 32, 32).tri_id >= 0
    alone0 = ops.rasterize_uv(uvs, faces[:1], 32, 32).tri_id >= 0
    assert (alone0 & alone1).any()
    assert (both[alone0] == 0).all()
    assert (both[alone1 & ~alone0] == 1).all()


def test_case4_watertight_uv_grid_with_vertices_on_texel_centres(stability):
    # 64 × 64 vertices on the texel centres of a 64 × 64 map; quads split along
    # alternating diagonals. Faces of one colour class share no vertex, so counting
    # coverage class by class counts every triangle that covers a texel.
    n = 64
    r, c = torch.meshgrid(
        torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij"
    )
    uvs = torch.stack([(c + 0.5) / n, 1 - (r + 0.5) / n], -1).reshape(-1, 2)
    faces, classes = grid(n)
    count = torch.zeros(n, n, dtype=torch.int64)
    for k in range(8):
        count += ops.rasterize_uv(uvs, faces[classes == k], n, n).tri_id >= 0
    wrong = int((count > 1).sum() + (count[1:-1, 1:-1] != 1).sum())
    stability.record(4, "64×64 UV grid: texels covered 0 or ≥ 2 times", wrong, 0)
    assert count.max() == 1
    assert (count[1:-1, 1:-1] == 1).all()
    whole = ops.rasterize_uv(uvs, faces, n, n)
    assert torch.equal(whole.tri_id >= 0, count == 1)
