"""accumulate_uv_error and nearest_covered_pixel: the kernel against the torch + OpenCV code
the sampling ran before it (``_reference``), bitwise, on a real render and on random
coverage and masks (sparse seeds make many ties), float32 and float64; no covered pixel, no
missed pixel, an empty mask, NaN in the image; bad input; the sampler's observe."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from test_model import camera, make_avatar
from urhead.errors import DTypeError, IndexRangeError, InvalidArgumentError, ShapeError
from urhead.head import procedural_head
from urhead.ops import _reference, accumulate_uv_error, nearest_covered_pixel

NAN = float("nan")


def _grids(fn, frame, side=16, start=0.25):
    """The (error, count) grids after ``fn`` adds ``frame`` to grids holding ``start``."""
    error = torch.full((side * side,), start, dtype=torch.float64)
    count = torch.full((side * side,), start, dtype=torch.float64)
    fn(frame.image, frame.target, frame.mask, frame.pixels, frame.uv, error, count)
    return error, count


def _assert_same(frame, side=16):
    ours, ref = (
        _grids(accumulate_uv_error, frame, side),
        _grids(_reference.accumulate_uv_error, frame, side),
    )
    for a, b in zip(ours, ref, strict=True):
        assert torch.equal(a.isnan(), b.isnan())
        assert torch.equal(a.nan_to_num(), b.nan_to_num()), (a - b).abs().nan_to_num().max()
    return ours


def _random_frame(h, w, rng, covered_fraction, mask_fraction, dtype=torch.float32, shuffle=False):
    covered = torch.from_numpy(rng.random(h * w) < covered_fraction)
    pixels = covered.nonzero()[:, 0]
    if shuffle:
        pixels = pixels[torch.from_numpy(rng.permutation(len(pixels)))]
    soft = torch.from_numpy(rng.uniform(0.3, 1.0, (h, w)))
    return SimpleNamespace(
        image=torch.from_numpy(rng.random((h, w, 3))).to(dtype),
        target=torch.from_numpy(rng.random((h, w, 3))).to(dtype),
        mask=(torch.from_numpy(rng.random((h, w)) < mask_fraction) * soft).to(dtype),
        pixels=pixels,
        uv=torch.from_numpy(rng.random((len(pixels), 2))).to(dtype),
    )


@pytest.fixture(scope="module")
def rendered():
    """A real render of the procedural head at 96², a mask the mesh falls short of (the
    coverage grown by 3 pixels: hair and silhouette misses) and a noisy target."""
    head = procedural_head(0)
    avatar = make_avatar(head, gaussians=False)
    with torch.no_grad():
        render = avatar.render(avatar.frame(3), camera(96))
    h, w = render.image.shape[:2]
    covered = torch.zeros(h * w)
    covered[render.mesh.pixels] = 1
    grown = torch.nn.functional.max_pool2d(covered.reshape(1, 1, h, w), 7, 1, 3)[0, 0]
    g = torch.Generator().manual_seed(0)
    return SimpleNamespace(
        image=render.image,
        target=render.image.detach() + 0.1 * torch.randn(h, w, 3, generator=g),
        mask=grown,
        pixels=render.mesh.pixels,
        uv=render.mesh.uv,
    )


def test_matches_the_previous_code_bitwise_on_a_real_render(rendered):
    covered = torch.zeros(rendered.mask.numel(), dtype=torch.bool)
    covered[rendered.pixels] = True
    missed = (rendered.mask.reshape(-1) > 0.5) & ~covered
    assert covered.sum() > 1000 and missed.sum() > 200
    for side in (16, 256):
        _, count = _assert_same(rendered, side)
        assert count.sum() - 0.25 * side * side == covered.sum() + missed.sum()
    as_float64 = SimpleNamespace(**{k: v.double() for k, v in vars(rendered).items()})
    as_float64.pixels = rendered.pixels
    _assert_same(as_float64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_the_previous_code_bitwise_on_random_frames(dtype):
    rng = np.random.default_rng(1)
    for trial in range(60):
        h, w = rng.integers(1, 50, 2)
        frame = _random_frame(
            h,
            w,
            rng,
            covered_fraction=rng.choice([0.005, 0.05, 0.4, 0.95]),
            mask_fraction=rng.choice([0.1, 0.7, 1.0]),
            dtype=dtype,
            shuffle=bool(trial % 2),
        )
        if len(frame.pixels):
            _assert_same(frame, side=int(rng.integers(1, 12)))


def test_nearest_covered_pixel_is_opencvs_including_ties():
    rng = np.random.default_rng(2)
    cases = []
    for _ in range(60):
        h, w = rng.integers(1, 60, 2)
        cases.append(torch.from_numpy(rng.random((h, w)) < rng.choice([0.002, 0.02, 0.3])))
    # Regular lattices: equidistant seeds everywhere.
    for step in (2, 3, 4, 7):
        lattice = torch.zeros(31, 29, dtype=torch.bool)
        lattice[::step, ::step] = True
        cases += [lattice, lattice.T.contiguous(), lattice.flip(0).contiguous()]
    for covered in cases:
        if covered.any():
            assert torch.equal(
                nearest_covered_pixel(covered), _reference.nearest_covered_pixel(covered)
            )
    assert nearest_covered_pixel(torch.zeros(3, 4, dtype=torch.bool)).eq(-1).all()


def test_no_covered_pixel_no_missed_pixel_empty_mask_and_nan(rendered, stability):
    # Nothing covered: nothing added.
    nothing = SimpleNamespace(**vars(rendered))
    nothing.pixels, nothing.uv = rendered.pixels[:0], rendered.uv[:0]
    error, count = _grids(accumulate_uv_error, nothing)
    assert error.eq(0.25).all() and count.eq(0.25).all()
    # No pixel the mesh misses: the covered ones alone.
    exact = SimpleNamespace(**vars(rendered))
    exact.mask = torch.zeros_like(rendered.mask).reshape(-1).index_fill(0, rendered.pixels, 1.0)
    exact.mask = exact.mask.reshape(rendered.mask.shape)
    _, count = _assert_same(exact)
    assert count.sum() - 0.25 * 256 == len(rendered.pixels)
    # An empty mask: covered pixels count, with zero error; no division anywhere.
    empty = SimpleNamespace(**vars(rendered))
    empty.mask = torch.zeros_like(rendered.mask)
    error, count = _assert_same(empty)
    assert error.eq(0.25).all() and count.sum() - 0.25 * 256 == len(rendered.pixels)
    # NaN in the image: the cells it reaches become NaN, as before; the others stay finite.
    poisoned = SimpleNamespace(**vars(rendered))
    poisoned.image = rendered.image.detach().clone()
    poisoned.image[40, 10:60, 1] = NAN  # covered and missed pixels of one row
    error, _ = _assert_same(poisoned)
    assert 0 < error.isnan().sum() < 40
    stability.checked(30, "UV error accumulation: empty mask, nothing covered, NaN image", 4)


def test_bad_input_is_refused_before_the_grids_change(rendered, stability):
    def refused(exception, match, side=16, **changes):
        frame = SimpleNamespace(**{**vars(rendered), **changes})
        error = torch.full((side * side,), 0.5, dtype=torch.float64)
        count = error.clone()
        with pytest.raises(exception, match=match):
            accumulate_uv_error(
                frame.image, frame.target, frame.mask, frame.pixels, frame.uv, error, count
            )
        assert error.eq(0.5).all() and count.eq(0.5).all()

    pixels, uv = rendered.pixels, rendered.uv
    refused(
        InvalidArgumentError,
        "pixels",
        pixels=torch.cat([pixels, pixels[:1]]),
        uv=torch.cat([uv, uv[:1]]),
    )
    refused(
        IndexRangeError,
        "pixels",
        pixels=torch.cat([pixels, torch.tensor([96 * 96])]),
        uv=torch.cat([uv, uv[:1]]),
    )
    refused(ShapeError, "uv", uv=uv[1:])
    refused(ShapeError, "mask", mask=rendered.mask[1:])
    refused(ShapeError, "image", image=rendered.image[..., :2])
    refused(DTypeError, "target", target=rendered.target.double())
    refused(DTypeError, "image", image=rendered.image.half())
    error = torch.zeros(15, dtype=torch.float64)
    with pytest.raises(ShapeError, match="square"):
        accumulate_uv_error(
            rendered.image, rendered.target, rendered.mask, pixels, uv, error, error
        )
    with pytest.raises(DTypeError, match="covered"):
        nearest_covered_pixel(torch.zeros(3, 3))
    stability.checked(26, "UV error accumulation: repeated/out-of-range pixels, shapes, dtypes", 9)


def test_the_sampler_observes_what_the_previous_code_charged(rendered):
    from dataclasses import replace

    from urhead.config import FitConfig
    from urhead.model import GaussianSampler

    config = replace(FitConfig(), uv_resolution=64, error_grid=32, initial_gaussians=0)
    sampler = GaussianSampler(config, procedural_head(0), 0)
    render = SimpleNamespace(
        image=rendered.image,
        mesh=SimpleNamespace(pixels=rendered.pixels, uv=rendered.uv),
        gaussians=None,
    )
    frame = SimpleNamespace(image=rendered.target, mask=rendered.mask)
    error = torch.zeros(32 * 32, dtype=torch.float64)
    count = error.clone()
    for _ in range(2):
        sampler.observe(render, frame)
        _reference.accumulate_uv_error(
            rendered.image,
            rendered.target,
            rendered.mask,
            rendered.pixels,
            rendered.uv,
            error,
            count,
        )
    assert torch.equal(sampler.accumulator.error, error)
    assert torch.equal(sampler.accumulator.count, count)


def test_an_observation_begun_before_its_step_is_judged_adds_only_when_applied(rendered):
    """The trainer begins the sampler's observation before the backward pass (the charge
    runs on a worker thread): applied, the grids are bit for bit those of observing at
    once, including on top of earlier frames; dropped (a rejected step), they are left
    alone; a kernel error surfaces when it is applied."""
    from dataclasses import replace

    from urhead.config import FitConfig
    from urhead.model import GaussianSampler

    config = replace(FitConfig(), uv_resolution=64, error_grid=32, initial_gaussians=0)
    at_once, begun = (GaussianSampler(config, procedural_head(0), 0) for _ in range(2))
    render = SimpleNamespace(
        image=rendered.image,
        mesh=SimpleNamespace(pixels=rendered.pixels, uv=rendered.uv),
        gaussians=None,
    )
    frame = SimpleNamespace(image=rendered.target, mask=rendered.mask)
    for applied in (True, False, True, True):
        observation = begun.start_observing(render, frame)
        if applied:
            at_once.observe(render, frame)
            begun.apply(observation)
        else:
            observation.charge.result()  # done, and never added
        assert torch.equal(begun.accumulator.error, at_once.accumulator.error)
        assert torch.equal(begun.accumulator.count, at_once.accumulator.count)
    assert at_once.accumulator.count.sum() > 0
    repeated = torch.cat([rendered.pixels, rendered.pixels[:1]])
    bad = SimpleNamespace(
        image=rendered.image,
        mesh=SimpleNamespace(pixels=repeated, uv=torch.cat([rendered.uv, rendered.uv[:1]])),
        gaussians=None,
    )
    observation = begun.start_observing(bad, frame)
    with pytest.raises(InvalidArgumentError, match="more than once"):
        begun.apply(observation)
    assert torch.equal(begun.accumulator.error, at_once.accumulator.error)
