"""Hostile inputs and failing writes (issue 14): each is refused by a typed error naming
the file or option, before any work; outputs are written whole or not at all."""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from urhead._atomic import (
    folder_lock,
    remove_stale_temporaries,
    write_bytes_atomically,
    write_directory_atomically,
)
from urhead._threads import num_threads, usable_cpus
from urhead.config import FitConfig
from urhead.data import DatasetError, load_subject
from urhead.data.images import read_png, write_png
from urhead.errors import InvalidArgumentError, SizeLimitError
from urhead.head import procedural_head, save_head
from urhead.head.pickle_compat import load_flame_pickle
from urhead.model import load_avatar
from urhead.train.checkpoint import save_checkpoint
from urhead.train.command import fit_subject
from urhead.train.memory import check_fit_memory
from urhead.train.trainer import Trainer
from use_avatar import make_use_avatar

TINY_FIT = FitConfig(uv_resolution=64, initial_gaussians=300, max_gaussians=450, eval_frames=1)
DEAD_PID = 2**22 + 12345  # above Linux's largest pid_max: never a running process


@pytest.fixture(scope="module")
def use(tmp_path_factory):
    return make_use_avatar(tmp_path_factory.mktemp("hardening"))


def _rewrite_npz(path, **changes):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def _gaussians(path):
    with np.load(path) as z:
        return {k: z[k].copy() for k in z.files}


def _nan_uv(a):
    uv = _gaussians(a / "gaussians.npz")["uv"]
    uv[0] = np.nan
    _rewrite_npz(a / "gaussians.npz", uv=uv)


def _uv_outside(a):
    uv = _gaussians(a / "gaussians.npz")["uv"]
    uv[0] = 7.0
    _rewrite_npz(a / "gaussians.npz", uv=uv)


def _bary_outside(a):
    bary = _gaussians(a / "gaussians.npz")["bary"]
    bary[0] = (2.0, -0.5, -0.5)
    _rewrite_npz(a / "gaussians.npz", bary=bary)


def _edit_meta(a, edit):
    meta = json.loads((a / "avatar.json").read_text())
    edit(meta)
    (a / "avatar.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("tamper", "file", "message"),
    [
        (_nan_uv, "gaussians.npz", "uv holds NaN"),
        (_uv_outside, "gaussians.npz", r"uv outside \[0, 1\]"),
        (_bary_outside, "gaussians.npz", "outside their triangle"),
        (lambda a: save_head(procedural_head(1), a / "head.npz"), "head.npz", "not the head"),
        (
            lambda a: _edit_meta(a, lambda m: m.update(background=[float("nan")] * 3)),
            "avatar.json",
            "background",
        ),
        (lambda a: _edit_meta(a, lambda m: m.pop("resolution")), "avatar.json", "resolution"),
        (lambda a: (a / "avatar.json").write_text("{"), "avatar.json", "JSON"),
        (lambda a: (a / "frames.npz").write_bytes(b"garbage"), "frames.npz", "frames.npz: "),
        (
            lambda a: (a / "maps.npy").write_bytes((a / "maps.npy").read_bytes()[:500]),
            "maps.npy",
            "not a readable|Failed to read",
        ),
    ],
)
def test_a_tampered_avatar_is_refused_naming_the_file(use, tmp_path, tamper, file, message):
    avatar = tmp_path / "avatar"
    shutil.copytree(use.avatar_dir, avatar)
    tamper(avatar)
    with pytest.raises(ValueError, match=message) as caught:
        load_avatar(avatar)
    assert str(avatar / file) in str(caught.value)


def test_a_non_rigid_camera_pose_is_refused(use, tmp_path):
    subject = shutil.copytree(use.subject_dir, tmp_path / "s")
    meta = json.loads((subject / "transforms_train.json").read_text())
    m = np.asarray(meta["frames"][0]["transform_matrix"])
    m[:3, :3] *= 1.5
    meta["frames"][0]["transform_matrix"] = m.tolist()
    (subject / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(
        DatasetError, match=r"transforms_train\.json: frames\[0\]\.transform_matrix"
    ):
        load_subject(subject)


@pytest.mark.parametrize("value", [float("nan"), -1.0, 0.0])
def test_prune_screen_fraction_must_be_positive(value):
    with pytest.raises(InvalidArgumentError, match="prune_screen_fraction"):
        FitConfig(prune_screen_fraction=value)


def test_thread_count_is_bounded_and_defaults_to_usable_cpus(monkeypatch):
    monkeypatch.setenv("URHEAD_NUM_THREADS", "100000")
    with pytest.raises(InvalidArgumentError, match="URHEAD_NUM_THREADS must be an integer from 1"):
        num_threads()
    assert 1 <= usable_cpus() <= len(os.sched_getaffinity(0))


def test_a_fit_too_large_for_memory_is_refused_with_the_estimate():
    with pytest.raises(SizeLimitError, match=r"--uv-resolution 8192: the fit needs about \d+"):
        check_fit_memory(FitConfig(uv_resolution=8192), available=16 << 30)
    check_fit_memory(FitConfig(uv_resolution=512), available=16 << 30)


def test_images_round_trip_through_a_path_that_is_not_utf8(tmp_path):
    folder = tmp_path / os.fsdecode(b"dir\xff")
    folder.mkdir()
    pixels = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    write_png(folder / "a.png", pixels)
    assert np.array_equal(np.rint(read_png(folder / "a.png") * 255).astype(np.uint8), pixels)


def test_a_full_disk_raises_and_leaves_no_file(tmp_path):
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8k", "tmpfs", str(disk)]).returncode:
        pytest.skip("cannot mount a small tmpfs here")
    try:
        with pytest.raises(OSError, match=r"out\.bin: cannot be written"):
            write_bytes_atomically(disk / "out.bin", b"x" * 100_000)
        assert list(disk.iterdir()) == []
        # A writer filling a folder fails in a plain write() that names no file: the
        # error names the folder being written.
        with pytest.raises(OSError, match=r"maps: cannot be written \(No space left"):
            write_directory_atomically(
                disk / "maps", lambda tmp: (tmp / "big.bin").write_bytes(b"x" * 100_000)
            )
        assert list(disk.iterdir()) == []
    finally:
        subprocess.run(["umount", str(disk)])


def test_stale_temporaries_of_dead_processes_are_removed(tmp_path):
    dead = tmp_path / f".checkpoint.tmp-{DEAD_PID}"
    live = tmp_path / f".avatar.tmp-{os.getpid()}"
    kept_old = tmp_path / f".kept.old-{DEAD_PID}"  # the newest copy while "kept" is missing
    for p in (dead, live, kept_old):
        p.mkdir()
    write_bytes_atomically(tmp_path / "x.json", b"{}")
    assert not dead.exists() and live.exists() and kept_old.exists()
    assert remove_stale_temporaries(tmp_path) == []


def test_out_is_locked_and_a_finished_fit_needs_force(use, tmp_path):
    out = tmp_path / "out"
    with folder_lock(out, "--out"), pytest.raises(InvalidArgumentError, match="another urhead"):
        fit_subject(use.subject_dir, out, TINY_FIT, progress=False)
    assert not (out / "avatar").exists()
    shutil.copytree(use.avatar_dir, out / "avatar")
    with pytest.raises(InvalidArgumentError, match="--force"):
        fit_subject(use.subject_dir, out, TINY_FIT, progress=False)


def test_head_file_mode_is_that_of_the_other_files(tmp_path):
    save_head(procedural_head(0), tmp_path / "head.npz")
    (tmp_path / "other").write_text("x")
    assert (tmp_path / "head.npz").stat().st_mode == (tmp_path / "other").stat().st_mode


def test_resume_refuses_another_head_or_subject(use, tmp_path):
    subject = load_subject(use.subject_dir)
    trainer = Trainer(subject, procedural_head(0), TINY_FIT, tmp_path, progress=False)
    state = trainer.start()
    save_checkpoint(tmp_path, state.avatar, trainer._checkpoint_state(state))
    other_head = Trainer(subject, procedural_head(1), TINY_FIT, tmp_path, progress=False)
    with pytest.raises(ValueError, match="another head than --head"):
        other_head.start(resume=True)
    retracked = shutil.copytree(use.subject_dir, tmp_path / "retracked")
    npz = sorted((retracked / "flame_param").glob("*.npz"))[0]
    with np.load(npz) as z:
        expr = z["expr"] + 0.1
    _rewrite_npz(npz, expr=expr)
    other_subject = Trainer(load_subject(retracked), procedural_head(0), TINY_FIT, tmp_path)
    with pytest.raises(ValueError, match="another subject than subject"):
        other_subject.start(resume=True)


def test_a_truncated_flame_pickle_names_the_file(tmp_path):
    path = tmp_path / "generic_model.pkl"
    path.write_bytes(b"\x80\x02}q\x00(X")
    with pytest.raises(ValueError, match=r"generic_model\.pkl: is not a readable FLAME pickle"):
        load_flame_pickle(path)


def test_an_older_checkpoint_without_fingerprints_resumes_and_is_still_checked(use, tmp_path):
    """Checkpoints written before they recorded their inputs: the head and the training
    timesteps they hold are compared instead."""
    subject = load_subject(use.subject_dir)
    trainer = Trainer(subject, procedural_head(0), TINY_FIT, tmp_path, progress=False)
    state = trainer.start()
    trainer.step(state)
    legacy = trainer._checkpoint_state(state)
    del legacy["inputs"]
    save_checkpoint(tmp_path, state.avatar, legacy)
    resumed = Trainer(subject, procedural_head(0), TINY_FIT, tmp_path, progress=False)
    assert resumed.start(resume=True).iteration == state.iteration == 1
    other_head = Trainer(subject, procedural_head(1), TINY_FIT, tmp_path, progress=False)
    with pytest.raises(ValueError, match="another head than --head"):
        other_head.start(resume=True)
    shorter = load_subject(use.subject_dir, test_last=len(subject.test) + 1)
    other_frames = Trainer(shorter, procedural_head(0), TINY_FIT, tmp_path, progress=False)
    with pytest.raises(ValueError, match="another subject than subject"):
        other_frames.start(resume=True)
