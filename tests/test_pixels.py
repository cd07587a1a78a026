"""covered_pixels and scatter_pixels: the kernels against their plain-torch references
(float64 values and gradients), finite differences, threads, bad input, and the avatar's
mesh branch against the torch expressions they replace."""

from __future__ import annotations

import pytest
import torch

from test_model import camera, make_avatar
from urhead.errors import DTypeError, InvalidArgumentError, ShapeError
from urhead.head import procedural_head
from urhead.ops import _reference, covered_pixels, rasterize, scatter_pixels

F64 = torch.float64


def _tri_id(h=37, w=301, seed=0):
    g = torch.Generator().manual_seed(seed)
    ids = torch.randint(-1, 50, (h, w), generator=g, dtype=torch.int32)
    ids[torch.rand(h, w, generator=g) < 0.4] = -1
    return ids


def test_covered_pixels_match_nonzero():
    for tri_id in (_tri_id(), _tri_id(1, 1), torch.full((4, 5), -1, dtype=torch.int32)):
        ours = covered_pixels(tri_id)
        assert ours.dtype == torch.int64
        assert torch.equal(ours, _reference.covered_pixels(tri_id))


def _case(h=37, w=301, c=4, dtype=F64, seed=0):
    pixels = covered_pixels(_tri_id(h, w, seed))
    g = torch.Generator().manual_seed(seed + 1)
    values = torch.randn(pixels.shape[0], c, generator=g, dtype=F64).to(dtype)
    background = torch.randn(c, generator=g, dtype=F64).to(dtype)
    return values, pixels, background, (h, w)


def _run(fn, case, weights, fill=None):
    values, pixels, background, size = case
    if fill is not None:  # the rows are the first C − K channels
        values = values[:, : background.shape[0] - fill.shape[0]]
    leaves = [values.clone().requires_grad_(True), background.clone().requires_grad_(True)]
    out = fn(leaves[0], pixels, leaves[1], size, fill=fill)
    (out * weights).sum().backward()
    return [out.detach()] + [x.grad for x in leaves]


@pytest.mark.parametrize(
    "channels, fill", [(1, None), (4, None), (4, [1.0]), (5, [-2.5, float("inf")])]
)
def test_scatter_matches_reference_float64(channels, fill):
    case = _case(c=channels)
    fill = None if fill is None else torch.tensor(fill, dtype=F64)
    weights = torch.randn(37, 301, channels, generator=torch.Generator().manual_seed(2), dtype=F64)
    ours = _run(scatter_pixels, case, weights, fill)
    ref = _run(_reference.scatter_pixels, case, weights, fill)
    for a, b in zip(ours, ref, strict=True):
        assert a.shape == b.shape
        assert torch.allclose(a, b, rtol=1e-14, atol=1e-12, equal_nan=True)
    assert torch.equal(ours[0], ref[0]) and torch.equal(ours[1], ref[1]), "copies are exact"
    if fill is not None:  # the listed pixels' tail is the fill, the rest the background
        image = ours[0].reshape(-1, channels)
        pixels, tail = case[1], -fill.shape[0]
        assert torch.equal(image[pixels, tail:], fill.expand(pixels.shape[0], -1))
        assert ours[1].shape == (pixels.shape[0], channels + tail)


@pytest.mark.parametrize("fill", [None, [1.0]])
def test_scatter_gradcheck_float64(fill):
    values, pixels, background, size = _case(5, 7, 3, seed=3)
    if fill is not None:
        fill = torch.tensor(fill, dtype=F64)
        values = values[:, :2].clone()
    assert torch.autograd.gradcheck(
        lambda v, b: scatter_pixels(v, pixels, b, size, fill=fill),
        (values.requires_grad_(True), background.requires_grad_(True)),
    )


def test_scatter_threads_agree_and_non_finite_values_are_data(monkeypatch, stability):
    values, pixels, background, size = _case(301, 257, 4, dtype=torch.float32, seed=4)
    values[0, 1] = float("nan")
    background[2] = float("inf")
    weights = torch.randn(301, 257, 4, generator=torch.Generator().manual_seed(5))
    runs = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        runs.append(_run(scatter_pixels, (values, pixels, background, size), weights))
    for run in runs[1:]:  # the same bits, the background's sum included
        assert all(
            torch.equal(a.view(torch.int32), b.view(torch.int32))
            for a, b in zip(run, runs[0], strict=True)
        )
    image = runs[0][0].reshape(-1, 4)
    assert image[pixels[0], 1].isnan() and image[pixels[0], [0, 2, 3]].isfinite().all()
    assert (image[pixels.max() + 1 :, 2] == float("inf")).all()
    stability.checked(27, "scatter_pixels: 1, 2, 3 threads, values and gradients", 4)


def test_bad_input_is_a_named_error(stability):
    values, pixels, background, size = _case(dtype=torch.float32)
    bad = [
        (ShapeError, "values", (values[0], pixels, background, size)),
        (ShapeError, "pixels", (values, pixels[:-1], background, size)),
        (ShapeError, "background", (values, pixels, background[:2], size)),
        (DTypeError, "background", (values, pixels, background.double(), size)),
        (DTypeError, "pixels", (values, pixels.int(), background, size)),
        (InvalidArgumentError, "pixels", (values, pixels.flip(0), background, size)),
        (InvalidArgumentError, "pixels", (values[:2], torch.tensor([3, 3]), background, size)),
        (InvalidArgumentError, "pixels", (values[:1], torch.tensor([37 * 301]), background, size)),
        (InvalidArgumentError, "pixels", (values[:1], torch.tensor([-1]), background, size)),
    ]
    ones = torch.ones(1)
    bad_fill = [  # values (P, 4) and a fill make 5 channels, not the background's 4
        (ShapeError, "background", (values, pixels, background, size, ones)),
        (DTypeError, "fill", (values[:, :3], pixels, background, size, ones.double())),
        (ShapeError, "fill", (values[:, :3], pixels, background, size, ones[0])),
        (
            InvalidArgumentError,
            "fill",
            (values[:, :3], pixels, background, size, torch.ones(1, requires_grad=True)),
        ),
        (InvalidArgumentError, "fill", (values[:, :0], pixels, background, size, torch.ones(4))),
    ]
    for error, name, args in bad + bad_fill:
        with pytest.raises(error, match=name):
            scatter_pixels(*args)
    with pytest.raises(ShapeError, match="tri_id"):
        covered_pixels(torch.zeros(3, dtype=torch.int32))
    with pytest.raises(DTypeError, match="tri_id"):
        covered_pixels(torch.zeros(3, 3, dtype=torch.int64))
    stability.checked(26, "scatter_pixels, covered_pixels: bad lists, shapes, dtypes, fills", 16)


def test_mesh_branch_image_is_the_torch_expression():
    """The avatar's mesh image before antialiasing: the covered pixels' colour (alpha 1)
    over the background (alpha 0), as ``repeat`` + ``index_put_`` built it."""
    avatar = make_avatar(procedural_head(), gaussians=False, resolution=64)
    cam = camera(48)
    params = avatar.frame(int(avatar.timesteps[0]))
    verts, rotations = avatar.skin(params)
    displaced, _ = avatar.displace(verts, rotations)
    raster = rasterize(displaced, avatar.tables().faces, cam)
    pixels = covered_pixels(raster.tri_id)
    assert pixels.numel() > 100
    rgb = torch.rand(pixels.shape[0], 3, dtype=torch.float32)
    rgba = torch.cat([rgb, rgb.new_ones(rgb.shape[0], 1)], 1)
    bg = torch.cat([avatar.background, avatar.background.new_zeros(1)])
    expected = bg.repeat(48 * 48, 1)
    expected[(raster.tri_id.reshape(-1) >= 0).nonzero()[:, 0]] = rgba
    assert torch.equal(scatter_pixels(rgba, pixels, bg, (48, 48)), expected.reshape(48, 48, 4))
    filled = scatter_pixels(rgb, pixels, bg, (48, 48), fill=rgb.new_ones(1))  # as the avatar
    assert torch.equal(filled, expected.reshape(48, 48, 4))
