"""Subjects exactly as VHAP's exporter writes them (tests/vhap_fixtures.py): monocular (an
empty val that still names timesteps) and multi-view (a held-out camera), what the reader
refuses in them and why, and urhead's own writer producing the same layout."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from test_data_io import make_camera, random_flame
from urhead.data import DatasetError, SubjectWriter, load_subject
from vhap_fixtures import vhap_camera, write_vhap_export


def edit_json(path, change):
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def test_monocular_export_opens_with_an_empty_val(tmp_path):
    root = write_vhap_export(tmp_path / "mono", num_timesteps=7)
    val = json.loads((root / "transforms_val.json").read_text())
    assert val["frames"] == [] and val["camera_indices"] == [] and val["timestep_indices"]
    subject = load_subject(root)
    assert subject.train.timesteps == [0, 1, 2, 3, 4]  # ceil(0.7 · 7) = 5
    assert subject.test.timesteps == [5, 6]
    assert len(subject.val) == 0
    frame = subject.test[1]
    assert frame.image.shape == (32, 40, 3) and frame.flame["static_offset"].shape == (1, 5143, 3)
    ref = vhap_camera(0)
    assert torch.allclose(frame.camera.K, ref.K)
    assert torch.allclose(frame.camera.viewmat, ref.viewmat, atol=1e-6)
    # VHAP's canonical jaw is float64; it is read as float32 like everything else
    assert subject.canonical_flame["jaw_pose"].dtype == np.float32


def test_multiview_export_holds_out_a_camera_as_val(tmp_path):
    root = write_vhap_export(tmp_path / "multi", num_timesteps=4, cameras=(0, 1, 2))
    subject = load_subject(root)
    pairs = lambda split: [(r.timestep, r.camera_index) for r in split.records]  # noqa: E731
    assert pairs(subject.train) == [(t, c) for t in range(3) for c in (0, 1)]
    assert pairs(subject.val) == [(t, 2) for t in range(3)]
    assert pairs(subject.test) == [(3, c) for c in (0, 1, 2)]
    for record in (*subject.train.records, *subject.val.records, *subject.test.records):
        ref = vhap_camera(record.camera_index)
        assert torch.allclose(record.camera.K, ref.K)
        assert torch.allclose(record.camera.viewmat, ref.viewmat, atol=1e-6)


def test_camera_8_is_the_held_out_one_when_there_is_one(tmp_path):
    root = write_vhap_export(tmp_path / "nersemble", num_timesteps=2, cameras=(7, 8, 9))
    subject = load_subject(root)
    assert {r.camera_index for r in subject.val.records} == {8}
    assert {r.camera_index for r in subject.train.records} == {7, 9}


def test_a_split_whose_lists_disagree_with_its_frames_is_explained(tmp_path):
    root = write_vhap_export(tmp_path / "multi", num_timesteps=4, cameras=(0, 1, 2))
    edit_json(root / "transforms_train.json", lambda m: m.update(camera_indices=[0]))
    expected = (
        r"transforms_train\.json: 'camera_indices' lists \[0\] but the frames use \[0, 1\]; "
        "a split file with frames must list exactly"
    )
    with pytest.raises(DatasetError, match=expected):
        load_subject(root)


def test_an_empty_split_may_name_timesteps_but_only_as_integers(tmp_path):
    root = write_vhap_export(tmp_path / "mono", num_timesteps=4)
    edit_json(root / "transforms_val.json", lambda m: m.update(timestep_indices=[0, 9, 12]))
    assert len(load_subject(root).val) == 0  # nothing to check the lists against
    edit_json(root / "transforms_val.json", lambda m: m.update(timestep_indices=["0", 1]))
    with pytest.raises(DatasetError, match=r"transforms_val\.json: 'timestep_indices' must be a "
                       "list of distinct integers"):  # fmt: skip
        load_subject(root)


def test_a_held_out_frame_that_is_also_trained_on_is_refused(tmp_path):
    root = write_vhap_export(tmp_path / "multi", num_timesteps=4, cameras=(0, 1, 2))
    train = json.loads((root / "transforms_train.json").read_text())

    def leak(meta):
        meta["frames"].append(train["frames"][0])
        meta["timestep_indices"] = sorted({*meta["timestep_indices"], 0})

    edit_json(root / "transforms_test.json", leak)
    with pytest.raises(DatasetError, match=r"transforms_test\.json: 1 of its frames are also in "
                       r"transforms_train\.json \(first: timestep 0, camera 0\)"):  # fmt: skip
        load_subject(root)


@pytest.mark.parametrize("num_timesteps", [4, 6, 7, 10])
def test_subject_writer_writes_the_layout_vhap_writes(tmp_path, num_timesteps):
    """File for file, the split lists and the frames' timesteps and cameras of urhead's
    writer match the VHAP fixture's."""
    vhap = write_vhap_export(tmp_path / "vhap", num_timesteps=num_timesteps)
    ours = tmp_path / "ours"
    rng = np.random.default_rng(0)
    with SubjectWriter(ours, make_camera()) as w:
        for t in range(num_timesteps):
            w.add_frame(t, np.ones((30, 40, 3)), np.ones((30, 40)), random_flame(rng))
    names = sorted(p.name for p in vhap.glob("*.json"))
    assert names == sorted(p.name for p in ours.glob("*.json"))
    for name in names:
        a, b = (json.loads((root / name).read_text()) for root in (vhap, ours))
        assert set(a) == set(b), name
        for key in ("timestep_indices", "camera_indices"):
            assert a[key] == b[key], (name, key)
        shape = lambda m: [(f["timestep_index"], f["camera_index"], sorted(f)) for f in m["frames"]]  # noqa: E731
        assert shape(a) == shape(b), name
