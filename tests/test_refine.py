"""Test-time refinement of held-out FLAME rows (urhead.eval.refine) and the evaluation's
refined scores: a perturbed frame is pulled back towards the parameters that made its
image, refinement never ends worse than it started, warm starts carry the correction,
and a trainable avatar is refused."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch

from test_model import camera, make_avatar
from urhead.eval import RefineSettings, evaluate_frames, refine_params, refine_sequence
from urhead.head import procedural_head
from urhead.model import FlameParams


@pytest.fixture(scope="module")
def head():
    return procedural_head(0)


def textured_avatar(head, **kwargs):
    """A tiny avatar whose colour map has a pattern (a grey head shows only its
    silhouette, which leaves the expression unobservable)."""
    avatar = make_avatar(head, **kwargs)
    r = avatar.resolution
    v, u = torch.meshgrid(torch.linspace(0, 1, r), torch.linspace(0, 1, r), indexing="ij")
    pattern = torch.stack(
        [torch.sin(23 * u), torch.cos(17 * v), torch.sin(11 * (u + v))], -1
    )  # SH DC units: ±1 is about ±0.28 in colour
    avatar.maps[..., 0:3] = avatar.maps[..., 0:3] + pattern
    return avatar


def _frame(avatar, params, timestep, cam):
    with torch.no_grad():
        image = avatar.render(params, cam).image.clamp(0, 1)
    mask = torch.ones(image.shape[:2])
    return SimpleNamespace(image=image, mask=mask, camera=cam, timestep=timestep, camera_index=0)


def _truth(avatar):
    e = avatar.num_expr
    expr = torch.zeros(e)
    expr[:3] = torch.tensor([0.4, -0.3, 0.2])
    pose = torch.zeros(15)
    pose[:3] = torch.tensor([0.05, 0.25, 0.0])  # pitch a little, turn the head
    pose[6] = 0.1  # jaw
    return FlameParams(expr, pose, torch.tensor([0.004, -0.003, 0.0]))


def _perturbed(p: FlameParams) -> FlameParams:
    pose = p.pose.clone()
    pose[:3] += torch.tensor([0.02, -0.03, 0.01])
    return FlameParams(p.expr.clone(), pose, p.transl + torch.tensor([0.003, 0.002, 0.0]))


def _pose_error(a: FlameParams, b: FlameParams) -> float:
    return float((a.pose[:3] - b.pose[:3]).norm() + 10 * (a.transl - b.transl).norm())


def test_refinement_moves_a_perturbed_frame_back_to_its_parameters(head):
    avatar = textured_avatar(head, resolution=64, count=400)
    cam = camera(64)
    truth = _truth(avatar)
    frame = _frame(avatar, truth, 100, cam)
    start = _perturbed(truth)
    out = refine_params(avatar, frame, start, RefineSettings(steps=40))
    assert _pose_error(out, truth) < 0.5 * _pose_error(start, truth)
    assert all(torch.isfinite(p).all() for p in out)
    assert not any(p.requires_grad for p in out)


def test_refinement_never_ends_worse_and_zero_steps_is_identity(head):
    avatar = textured_avatar(head, resolution=32, count=100)
    cam = camera(48)
    truth = _truth(avatar)
    frame = _frame(avatar, truth, 100, cam)
    # Rates so large that Adam overshoots: the best state seen (the start) is kept.
    wild = RefineSettings(steps=3, lr_expression=50.0, lr_pose=5.0, lr_translation=5.0)
    out = refine_params(avatar, frame, truth, wild)
    assert all(torch.equal(a, b) for a, b in zip(out, truth, strict=True))
    same = refine_params(avatar, frame, truth, RefineSettings(steps=0, full_steps=0))
    assert same is truth
    plain = evaluate_frames(
        avatar, [frame], params=[truth], refine=RefineSettings(steps=0, full_steps=0)
    )
    assert plain.psnr_refined is None


def test_refinement_refuses_a_trainable_avatar(head):
    avatar = textured_avatar(head, resolution=32, count=50)
    cam = camera(32)
    frame = _frame(avatar, _truth(avatar), 100, cam)
    avatar.maps.requires_grad_(True)
    with pytest.raises(ValueError, match="frozen avatar"):
        refine_params(avatar, frame, _truth(avatar), RefineSettings(steps=1))


def test_warm_start_carries_the_previous_correction(head):
    avatar = textured_avatar(head, resolution=32, count=100)
    cam = camera(48)
    truth = _truth(avatar)
    frames = [_frame(avatar, truth, t, cam) for t in (100, 101)]
    starts = [_perturbed(truth), _perturbed(truth)]
    calls = []
    # A budget the cold start cannot converge in: 15 steps take both starts to the same
    # plateau (pose error 0.0358 either way); at 8, warm 0.037 vs cold 0.051.
    budget = RefineSettings(steps=8, full_steps=0)
    warm = refine_sequence(avatar, frames, starts, budget, progress=lambda: calls.append(1))
    cold = refine_sequence(avatar, frames, starts, replace(budget, warm_start=False))
    assert len(calls) == 2
    # The second frame is identical to the first: warm, it starts where the first ended
    # and gets closer than a cold start with the same budget.
    assert _pose_error(warm[1], truth) < _pose_error(cold[1], truth)
    assert torch.equal(warm[0].pose, cold[0].pose)


def test_evaluate_frames_reports_both_conventions_and_refined_scores(head):
    avatar = textured_avatar(head, resolution=32, count=150)
    cam = camera(48)
    truth = _truth(avatar)
    frame = _frame(avatar, truth, 100, cam)
    frame.mask = torch.zeros(48, 48)
    frame.mask[8:40, 8:40] = 1.0
    e = avatar.num_expr
    tracked = _perturbed(truth)
    frame.flame = {
        "expr": tracked.expr[None].numpy(),
        "rotation": tracked.pose[None, 0:3].numpy(),
        "neck_pose": tracked.pose[None, 3:6].numpy(),
        "jaw_pose": tracked.pose[None, 6:9].numpy(),
        "eyes_pose": tracked.pose[None, 9:15].numpy(),
        "translation": tracked.transl[None].numpy(),
    }
    assert e == tracked.expr.numel()
    plain = evaluate_frames(avatar, [frame])
    assert plain.psnr_refined is None
    scores = evaluate_frames(avatar, [frame], refine=RefineSettings(steps=30))
    assert scores.psnr == pytest.approx(plain.psnr)
    # Background pixels are nearly free: the full-image PSNR reads higher.
    assert scores.psnr_full > scores.psnr
    assert scores.psnr_refined > scores.psnr + 1.0
    assert scores.psnr_refined_full > scores.psnr_full


def test_refinement_on_a_resampled_frame_improves_the_full_size_image(head):
    from urhead.losses import psnr

    avatar = textured_avatar(head, resolution=64, count=400)
    cam = camera(128)
    truth = _truth(avatar)
    frame = _frame(avatar, truth, 100, cam)
    start = _perturbed(truth)
    out = refine_params(avatar, frame, start, RefineSettings(steps=40, max_side=64))

    def score(p):
        with torch.no_grad():
            return float(psnr(avatar.render(p, cam).image.clamp(0, 1), frame.image))

    assert score(out) > score(start) + 2.0
    assert _pose_error(out, truth) < 0.65 * _pose_error(start, truth)


def test_a_resized_camera_projects_to_scaled_pixel_coordinates():
    cam = camera(128)
    small = cam.resized(64, 32)
    points = torch.tensor([[0.01, -0.02, 0.05], [0.0, 0.03, -0.02]])
    uv, _ = cam.project(points)
    uv_small, _ = small.project(points)
    assert torch.allclose(uv_small, uv * torch.tensor([0.5, 0.25]), atol=1e-4)
    assert (small.width, small.height) == (64, 32)


def test_exact_flame_scores_reads_the_ground_truth_file(head, tmp_path):
    import numpy as np

    from urhead.eval import exact_flame_scores

    avatar = textured_avatar(head, resolution=32, count=100)
    cam = camera(48)
    truth = _truth(avatar)
    frame = _frame(avatar, truth, 2, cam)
    # synthetic_ground_truth.npz holds every timestep: the frame's row is index 2
    rows = lambda x: np.stack([np.zeros_like(x), np.zeros_like(x), x])  # noqa: E731
    path = tmp_path / "synthetic_ground_truth.npz"
    np.savez(path, expr=rows(truth.expr.numpy()), pose=rows(truth.pose.numpy()),
             transl=rows(truth.transl.numpy()))  # fmt: skip
    exact = exact_flame_scores(avatar, [frame], path)
    direct = evaluate_frames(avatar, [frame], params=[truth], mesh_only=False)
    assert exact.psnr == direct.psnr and exact.psnr_full == direct.psnr_full
    assert exact.psnr_full > 40  # the frame was rendered from exactly these parameters


def test_full_size_steps_finish_what_the_coarse_steps_leave(head):
    """A pose found on a 4× reduced frame leaves sub-pixel misalignment at full size;
    steps at full size remove more of it than the same number of extra coarse steps."""
    from urhead.losses import psnr

    avatar = textured_avatar(head, resolution=64, count=400)
    cam = camera(128)
    truth = _truth(avatar)
    frame = _frame(avatar, truth, 100, cam)
    start = _perturbed(truth)

    def score(settings):
        p = refine_params(avatar, frame, start, settings)
        with torch.no_grad():
            return float(psnr(avatar.render(p, cam).image.clamp(0, 1), frame.image))

    coarse = score(RefineSettings(steps=40, full_steps=0, max_side=32))
    more_coarse = score(RefineSettings(steps=50, full_steps=0, max_side=32))
    fine = score(RefineSettings(steps=40, full_steps=10, max_side=32))
    assert fine > max(coarse, more_coarse) + 0.5
    with pytest.raises(ValueError, match="full_steps"):
        RefineSettings(full_steps=-1)


def test_the_coarse_stage_goes_on_while_its_loss_still_falls_and_no_further(head, monkeypatch):
    """Far from the optimum the reduced-size stage takes more than ``steps`` (up to
    ``coarse_max_steps``) and ends nearer; a threshold no step can meet keeps ``steps``."""
    avatar = textured_avatar(head, resolution=64, count=400)
    cam = camera(64)
    truth = _truth(avatar)
    frame = _frame(avatar, truth, 100, cam)
    start = _perturbed(truth)
    counted = []
    adam_step = torch.optim.Adam.step

    def counting_step(self, *args, **kwargs):
        counted[-1] += 1
        return adam_step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", counting_step)

    def run(**kwargs):
        counted.append(0)
        settings = RefineSettings(steps=3, full_steps=0, max_side=64, **kwargs)
        return refine_params(avatar, frame, start, settings)

    fixed = run(coarse_max_steps=15, coarse_min_gain=1.0)
    adaptive = run(coarse_max_steps=15, coarse_min_gain=0.01)
    assert counted[0] == 3
    assert 3 < counted[1] <= 15
    assert _pose_error(adaptive, truth) < _pose_error(fixed, truth)
    with pytest.raises(ValueError, match="coarse_max_steps"):
        RefineSettings(coarse_max_steps=-1)
    with pytest.raises(ValueError, match="coarse_min_gain"):
        RefineSettings(coarse_min_gain=float("nan"))
