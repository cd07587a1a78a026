"""The fit end to end on a tiny synthetic subject: it learns, writes the avatar directory and
the PSNR-vs-time log, resumes after kill -9 to the same bits, and leaves out what a scene
does not need."""

from __future__ import annotations

import csv
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch

from urhead.cli import main
from urhead.config import FitConfig
from urhead.data import load_subject
from urhead.data.synth.subject import SynthConfig, synthesize
from urhead.eval.metrics import evaluate_frames, frame_params
from urhead.eval.stlpips import load_stlpips
from urhead.head import procedural_head
from urhead.model import load_avatar
from urhead.train.checkpoint import find_checkpoint, save_checkpoint
from urhead.train.trainer import Trainer, eval_subset, frame_order, uv_lr_factor

TINY = SynthConfig(
    frames=10, resolution=64, seed=5, difficulty="easy", samples_per_side=1, edge_samples_per_side=1
)
SMALL_FIT = FitConfig(
    iterations=40,
    uv_resolution=64,
    initial_gaussians=300,
    max_gaussians=450,
    sample_every=10,
    sample_cap=60,
    error_grid=32,
    lr_decay_start=20,
    lr_color=5e-3,
    lr_displacement=1e-4,
    color_init_frames=2,
    eval_every_seconds=0.0,
    eval_frames=2,
    checkpoint_every=10,
)


@pytest.fixture(scope="module")
def subject_dir(tmp_path_factory):
    return synthesize(tmp_path_factory.mktemp("fit") / "subject", TINY, progress=False)


@pytest.fixture(scope="module")
def head():
    return procedural_head(0)


@pytest.fixture(scope="module")
def fitted(subject_dir, head, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit_out")
    result = Trainer(load_subject(subject_dir), head, SMALL_FIT, out, progress=False).run()
    return result


def test_fit_learns_and_writes_its_outputs(fitted):
    out = fitted.out
    with open(out / "psnr_vs_time.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["seconds", "iteration", "psnr"]
    history = [(float(s), int(i), float(p)) for s, i, p in rows[1:]]
    assert len(history) == SMALL_FIT.iterations  # eval_every_seconds = 0: every iteration
    assert all(b[0] >= a[0] and b[1] == a[1] + 1 for a, b in itertools.pairwise(history))
    first, last = history[0][2], history[-1][2]
    assert last > first + 1.0, f"held-out PSNR went {first:.2f} → {last:.2f} dB"
    assert (out / "psnr_vs_time.png").stat().st_size > 1000
    metrics = json.loads((out / "metrics.json").read_text())
    for key in (
        "psnr",
        "ssim",
        "lpips",
        "psnr_mesh_only",
        "num_gaussians",
        "seconds",
        "iterations",
    ):
        assert key in metrics
    assert metrics["lpips"] is None
    assert metrics["iterations"] == SMALL_FIT.iterations
    assert 0 < metrics["num_gaussians"] <= SMALL_FIT.max_gaussians
    assert 0 < metrics["ssim"] <= 1
    avatar = load_avatar(out / "avatar")
    assert avatar.num_gaussians == metrics["num_gaussians"]
    assert torch.equal(avatar.maps, fitted.avatar.maps.detach())
    assert json.loads((out / "avatar" / "avatar.json").read_text())["config"] == asdict(SMALL_FIT)


def test_result_carries_the_refined_parameters_it_scored(fitted, subject_dir):
    subject = load_subject(subject_dir)
    held = list(subject.test if len(subject.test) else subject.val)
    assert set(fitted.refined) == {(f.timestep, f.camera_index) for f in held}
    params = [fitted.refined[(f.timestep, f.camera_index)] for f in held]
    tracked = [fitted.avatar.params_from_flame(f.flame) for f in held]
    assert any(not torch.equal(p.pose, t.pose) for p, t in zip(params, tracked, strict=True))
    scores = evaluate_frames(fitted.avatar, held, params=params, mesh_only=False)
    metrics = json.loads((fitted.out / "metrics.json").read_text())
    assert scores.psnr == pytest.approx(metrics["psnr_refined"], abs=1e-9)


def test_metrics_carry_stlpips_of_the_held_out_frames(fitted, subject_dir):
    """``stlpips_alex`` in metrics.json is ST-LPIPS-alex inside the mask over the
    ``eval_frames`` held-out frames spread evenly over the sequence, as ``urhead eval``
    scores a frame: recomputed here from the saved avatar."""
    metrics = json.loads((fitted.out / "metrics.json").read_text())
    metric, note = load_stlpips()
    assert metric is not None, note
    avatar = load_avatar(fitted.out / "avatar")
    subject = load_subject(subject_dir)
    held_out = list(subject.test if len(subject.test) else subject.val)
    picked = [held_out[i] for i in eval_subset(held_out, SMALL_FIT.eval_frames)]
    assert metrics["stlpips_frames"] == len(picked)
    scores = []
    with torch.no_grad():
        for frame in picked:
            image = avatar.render(frame_params(avatar, frame), frame.camera).image.clamp(0, 1)
            scores.append(metric(image, frame.image, frame.mask))
    assert metrics["stlpips_alex"] == pytest.approx(sum(scores) / len(scores), rel=1e-5)
    assert 0 < metrics["stlpips_alex"] < 1
    assert "stlpips_skipped" not in metrics


def test_metrics_record_why_stlpips_is_missing(subject_dir, head, tmp_path, monkeypatch):
    note = "ST-LPIPS skipped: the stlpips-pytorch package (its weights) is missing"
    monkeypatch.setattr("urhead.train.trainer.load_stlpips", lambda: (None, note))
    config = replace(SMALL_FIT, iterations=2, refine_steps=0, refine_full_steps=0)
    Trainer(load_subject(subject_dir), head, config, tmp_path, progress=False).run()
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["stlpips_alex"] is None
    assert metrics["stlpips_skipped"] == note


def test_sampling_respects_cap_and_budget(fitted):
    avatar = fitted.avatar
    assert avatar.num_gaussians <= SMALL_FIT.max_gaussians
    # Every Gaussian sits on the atlas and its barycentrics reproduce its UV point.
    uv_faces = torch.from_numpy(avatar.head.uv_faces.astype(np.int64))
    corners = torch.tensor(avatar.head.uv_coords)[uv_faces[avatar.gaussian_face]]
    rebuilt = (corners * avatar.gaussian_bary[:, :, None]).sum(1)
    assert torch.allclose(rebuilt, avatar.gaussian_uv, atol=1e-5)


def test_frame_params_move_only_for_trained_rows(fitted, subject_dir):
    subject = load_subject(subject_dir)
    from urhead.model import frame_table

    _, tracked = frame_table(subject.train, fitted.avatar.num_expr)
    moved = (fitted.avatar.frame_params != tracked).any(1)
    assert moved.all(), "every training frame was visited and refined"


def test_uv_decay_and_frame_order():
    c = replace(SMALL_FIT, iterations=100, lr_decay_start=50, lr_decay_final=0.1)
    assert uv_lr_factor(c, 0) == 1.0 and uv_lr_factor(c, 50) == 1.0
    assert uv_lr_factor(c, 100) == pytest.approx(0.1)
    assert uv_lr_factor(c, 75) == pytest.approx(0.1**0.5)
    order = frame_order(0, 3, 7)
    assert sorted(order.tolist()) == list(range(7))
    assert np.array_equal(order, frame_order(0, 3, 7))


def _fit_command(subject_dir, out, *extra):
    return [
        sys.executable,
        "-m",
        "urhead.cli",
        "fit",
        str(subject_dir),
        "--out",
        str(out),
        "--quiet",
        "--iterations",
        "150",
        "--uv-resolution",
        "64",
        "--initial-gaussians",
        "200",
        "--max-gaussians",
        "300",
        "--sample-every",
        "10",
        "--sample-cap",
        "50",
        "--color-init-frames",
        "1",
        "--eval-frames",
        "1",
        "--eval-every-seconds",
        "1000",
        "--checkpoint-every",
        "5",
        *extra,
    ]


def test_resume_after_kill_9_reaches_the_same_result(subject_dir, tmp_path):
    env = dict(os.environ, URHEAD_NUM_THREADS="1", OMP_NUM_THREADS="1")
    straight = tmp_path / "straight"
    subprocess.run(_fit_command(subject_dir, straight), check=True, env=env, capture_output=True)

    killed = tmp_path / "killed"
    proc = subprocess.Popen(_fit_command(subject_dir, killed), env=env, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline:
        ckpt = find_checkpoint(killed)
        if ckpt is not None and (ckpt / "state.pt").is_file():
            state = torch.load(ckpt / "state.pt", weights_only=True)
            if state["iteration"] >= 20:
                break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (killed / "metrics.json").exists(), "the kill came too late to test resuming"
    resumed = subprocess.run(
        _fit_command(subject_dir, killed, "--resume"), env=env, capture_output=True, text=True
    )
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming from" in resumed.stderr
    a, b = load_avatar(straight / "avatar"), load_avatar(killed / "avatar")
    assert torch.equal(a.maps, b.maps)
    assert torch.equal(a.gaussian_uv, b.gaussian_uv)
    assert torch.equal(a.frame_params, b.frame_params)


def test_resume_with_other_settings_is_refused(subject_dir, fitted, tmp_path, capsys):
    other = replace(SMALL_FIT, sample_cap=7)
    save_checkpoint(tmp_path, fitted.avatar, {"config": asdict(other), "iteration": 3})
    args = _fit_command(subject_dir, tmp_path)[3:]
    assert main([*args, "--resume"]) == 1
    assert "different configuration" in capsys.readouterr().err
    assert not (tmp_path / "avatar").exists()


def test_a_fit_resumes_with_its_moments_stored_the_other_way(subject_dir, head, tmp_path):
    """``map_moments`` is storage, not model: a checkpoint with float32 moments resumes
    into a bfloat16 fit (moments rounded to nearest, the rest as saved) and back."""
    config = replace(SMALL_FIT, map_moments="float32")
    trainer = Trainer(load_subject(subject_dir), head, config, tmp_path, progress=False)
    state = trainer.start()
    for _ in range(4):
        trainer.step(state)
    state.guard.settle(state.iteration)
    save_checkpoint(tmp_path, state.avatar, trainer._checkpoint_state(state))
    saved = torch.load(find_checkpoint(tmp_path) / "state.pt", weights_only=True)
    saved_moments = saved["maps_opt"]["state"][0]
    assert saved_moments["exp_avg_sq"].dtype == torch.float32
    for kind, dtype in (("bfloat16", torch.bfloat16), ("float32", torch.float32)):
        resumed = replace(config, map_moments=kind)
        state = Trainer(load_subject(subject_dir), head, resumed, tmp_path, progress=False).start(
            resume=True
        )
        assert state.iteration == saved["iteration"] == 4
        moments = state.maps_opt.state[state.avatar.maps]
        for name in ("exp_avg", "exp_avg_sq"):
            assert moments[name].dtype == dtype
            assert torch.equal(moments[name], saved_moments[name].to(dtype))
    # A checkpoint from before the field existed (its config has no map_moments) resumes.
    older = trainer._checkpoint_state(state)
    del older["config"]["map_moments"]
    save_checkpoint(tmp_path, state.avatar, older)
    resumed = Trainer(load_subject(subject_dir), head, SMALL_FIT, tmp_path, progress=False)
    assert resumed.start(resume=True).iteration == 4


def test_mesh_only_fit_has_no_gaussian_state(subject_dir, head, tmp_path, caplog):
    config = replace(SMALL_FIT, iterations=6, gaussians=False, normal_loss=False)
    with caplog.at_level("INFO", logger="urhead.fit"):
        result = Trainer(load_subject(subject_dir), head, config, tmp_path, progress=False).run()
    avatar = result.avatar
    assert avatar.layout.channels == 3 * 16 + 4
    assert avatar.num_gaussians == 0
    assert result.metrics["psnr"] == pytest.approx(result.metrics["psnr_mesh_only"])
    assert "Gaussian branch" in caplog.text and "normal loss" in caplog.text


def test_bad_subject_fails_before_any_work(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["fit", str(tmp_path / "nowhere"), "--out", str(out)]) == 1
    assert "nowhere" in capsys.readouterr().err
    assert not out.exists()
