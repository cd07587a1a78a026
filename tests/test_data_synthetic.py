"""Synthetic subjects on a tiny configuration: readable by load_subject, deterministic from
the seed, cached by key, geometrically consistent with their ground-truth parameters."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from urhead.cli import main
from urhead.data import load_subject
from urhead.data.reader import Subject
from urhead.data.synth.subject import SynthConfig, contact_sheet, synthesize
from urhead.head import load_head

TINY = SynthConfig(
    frames=4, resolution=48, seed=3, difficulty="easy", samples_per_side=1, edge_samples_per_side=2
)


@pytest.fixture(scope="module")
def tiny_subject(tmp_path_factory):
    return synthesize(tmp_path_factory.mktemp("synth") / "s", TINY, progress=False)


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_subject_loads_with_normals_noisy_flame_and_its_head(tiny_subject):
    subject = load_subject(tiny_subject)
    assert (subject.width, subject.height) == (48, 48)
    assert subject.has_normals and len(subject.train) == 3 and len(subject.test) == 1
    frame = subject.train[1]
    fg = frame.mask > 0.5
    assert 0.1 < fg.float().mean() < 0.9
    # White background outside the head; normals exactly where something was hit.
    assert torch.all(frame.image[frame.mask == 0] == 1.0)
    assert torch.equal(frame.normals.abs().sum(-1) > 0, frame.mask > 0)
    # Normals face the camera (OpenCV z < 0) on most of the head.
    assert (frame.normals[fg][:, 2] < 0).float().mean() > 0.9
    head = load_head(tiny_subject / "head.npz")
    truth = np.load(tiny_subject / "synthetic_ground_truth.npz")
    assert frame.flame["expr"].shape == (1, head.num_expr)
    assert frame.flame["shape"].shape == (head.num_shape,)
    # The exported parameters are the truth plus tracking noise: close, not equal.
    error = np.abs(frame.flame["rotation"][0] - truth["pose"][1, :3])
    assert 0 < error.max() < 0.05
    assert not np.array_equal(frame.flame["shape"], truth["shape"])


def test_ground_truth_vertices_project_into_the_mask(tiny_subject):
    """Skin the head with the exact parameters and project it with the subject's camera:
    the face vertices land on foreground pixels."""
    subject = load_subject(tiny_subject)
    head = load_head(tiny_subject / "head.npz")
    truth = np.load(tiny_subject / "synthetic_ground_truth.npz")
    for frame in [*subject.train, *subject.test]:
        t = frame.timestep
        out = head.skin(
            shape=torch.from_numpy(truth["shape"]),
            expr=torch.from_numpy(truth["expr"][t]),
            pose=torch.from_numpy(truth["pose"][t]),
            transl=torch.from_numpy(truth["transl"][t]),
        )
        face = torch.from_numpy(head.region_vertices("face"))
        uv, depth = frame.camera.project(out.verts[0, face])
        assert (depth > 0).all()
        cols, rows = uv[:, 0].long(), uv[:, 1].long()
        inside = (cols >= 0) & (cols < 48) & (rows >= 0) & (rows < 48)
        assert inside.all()
        # One sample per pixel: a vertex at the silhouette may sit in a pixel whose centre
        # ray misses, so allow the neighbouring pixel (a 3 × 3 dilation of the mask).
        grown = torch.nn.functional.max_pool2d(frame.mask[None, None], 3, 1, 1)[0, 0]
        assert (grown[rows, cols] > 0).all()
        assert (frame.mask[rows, cols] > 0).float().mean() > 0.85


def test_same_seed_same_bytes_other_seed_other_subject(tiny_subject, tmp_path):
    again = synthesize(tmp_path / "again", TINY, progress=False)
    assert _files(again) == _files(tiny_subject)
    other = synthesize(
        tmp_path / "other", SynthConfig(**{**TINY.__dict__, "seed": 4}), progress=False
    )
    a = load_subject(tiny_subject).train[0].image
    b = load_subject(other).train[0].image
    assert not torch.equal(a, b)


def test_same_bytes_for_any_thread_count(tiny_subject, tmp_path):
    """Frames are traced on all threads while a helper thread meshes and writes others,
    with a BVH refit between rebuilds: none of it may change a byte."""
    code = (
        "import sys\n"
        "from urhead.data.synth.subject import SynthConfig, synthesize\n"
        f"synthesize(sys.argv[1], SynthConfig(**{TINY.__dict__!r}), progress=False)\n"
    )
    for threads in ("1", "3"):
        out = tmp_path / threads
        env = {**os.environ, "URHEAD_NUM_THREADS": threads}
        subprocess.run([sys.executable, "-c", code, str(out)], env=env, check=True)
        assert _files(out) == _files(tiny_subject)


def test_cache_reuses_a_matching_subject_and_replaces_a_stale_one(tmp_path, capsys):
    out = tmp_path / "s"
    args = ["synth", "--out", str(out), "--frames", "3", "--resolution", "32", "--seed", "1"]
    args += ["--difficulty", "easy", "--samples", "1", "--edge-samples", "1", "--quiet"]
    assert main(args) == 0
    stamp = (out / "images" / "00000_00.png").stat().st_mtime_ns
    assert main(args) == 0
    assert "reused (cached)" in capsys.readouterr().out
    assert (out / "images" / "00000_00.png").stat().st_mtime_ns == stamp
    assert main([*args[:-1], "--frames", "4", "--quiet"]) == 0
    assert json.loads((out / "synthetic.json").read_text())["config"]["frames"] == 4
    assert len(load_subject(out, test_last=1).train) == 3


@pytest.mark.parametrize("damage", ["truncate_image", "edit_image", "drop_manifest"])
def test_cache_remakes_a_damaged_subject(tiny_subject, tmp_path, damage, capsys, caplog):
    """A cached subject whose files no longer match its manifest is made again, never
    reused; the CLI says so."""
    out = tmp_path / "s"
    shutil.copytree(tiny_subject, out)
    image = out / "images" / "00001_00.png"
    if damage == "truncate_image":
        image.write_bytes(image.read_bytes()[:100])
    elif damage == "edit_image":  # same size, one byte changed
        data = bytearray(image.read_bytes())
        data[-20] ^= 0xFF
        image.write_bytes(bytes(data))
    else:
        (out / "manifest.json").unlink()
    args = ["synth", "--out", str(out), "--frames", str(TINY.frames), "--quiet"]
    args += ["--resolution", str(TINY.resolution), "--seed", str(TINY.seed)]
    args += ["--difficulty", TINY.difficulty, "--samples", "1", "--edge-samples", "2"]
    assert main(args) == 0
    assert capsys.readouterr().out.startswith("wrote ")
    assert "making it again" in caplog.text
    assert _files(out) == _files(tiny_subject)
    assert main(args) == 0
    assert capsys.readouterr().out.startswith("reused (cached) ")


def test_refuses_to_replace_a_folder_that_is_not_a_subject(tmp_path):
    (tmp_path / "precious").mkdir()
    with pytest.raises(FileExistsError, match="not a synthetic subject"):
        synthesize(tmp_path / "precious", TINY, progress=False)
    with pytest.raises(ValueError, match="difficulty must be one of"):
        SynthConfig(difficulty="impossible")


def test_contact_sheet_decodes_only_the_frames_it_shows(tiny_subject, tmp_path, monkeypatch):
    decoded = []
    decode = Subject._decode
    monkeypatch.setattr(Subject, "_decode", lambda self, r: decoded.append(r) or decode(self, r))
    path = contact_sheet(tiny_subject, tmp_path / "sheet.png", columns=2, rows=1, tile=32)
    assert sorted(r.timestep for r in decoded) == [0, 3]
    sheet = np.asarray(Image.open(path))
    assert sheet.shape == (32, 64, 3)
    # Each tile shows the head: not all background.
    assert (sheet[:, :32] < 250).any() and (sheet[:, 32:] < 250).any()
