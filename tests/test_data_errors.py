"""urhead.data.load_subject on broken subjects: every problem is an error naming the file,
raised when the subject is opened where that is possible."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from test_data_io import random_flame, write_subject
from urhead.data import DatasetError, MissingFileError, load_subject


@pytest.fixture
def subject_root(tmp_path):
    root = tmp_path / "s"
    write_subject(root, num_frames=4, normals=True)
    return root


def edit_json(path, change):
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))


def test_missing_image_is_named_at_load_time(subject_root):
    (subject_root / "images" / "00002_00.png").unlink()
    with pytest.raises(MissingFileError, match=r"images/00002_00\.png: not found \(file_path"):
        load_subject(subject_root)


def test_missing_mask_and_flame_file(subject_root):
    (subject_root / "fg_masks" / "00001_00.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"fg_masks/00001_00\.png"):
        load_subject(subject_root)


def test_missing_flame_file(subject_root):
    (subject_root / "flame_param" / "00003.npz").unlink()
    with pytest.raises(MissingFileError, match=r"flame_param/00003\.npz"):
        load_subject(subject_root)


def test_missing_split_file_and_folder(subject_root, tmp_path):
    (subject_root / "transforms_train.json").unlink()
    with pytest.raises(MissingFileError, match=r"transforms_train\.json.*test_last"):
        load_subject(subject_root)
    assert len(load_subject(subject_root, test_last=1).train) == 3  # transforms.json suffices
    with pytest.raises(MissingFileError, match="nowhere"):
        load_subject(tmp_path / "nowhere")


def test_corrupt_json(subject_root):
    (subject_root / "transforms_test.json").write_text("{not json")
    with pytest.raises(DatasetError, match=r"transforms_test\.json: is not valid JSON"):
        load_subject(subject_root)


@pytest.mark.parametrize(
    ("change", "pattern"),
    [
        (lambda m: m.pop("fl_x"), r"missing top-level keys \['fl_x'\]"),
        (lambda m: m["frames"][1].pop("transform_matrix"), r"frames\[1\] is missing keys"),
        (
            lambda m: m["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]),
            r"transform_matrix must be 4×4",
        ),
        (
            lambda m: m["frames"][0].update(fl_x="fast"),
            r"frames\[0\]\.fl_x must be a finite float",
        ),
        (lambda m: m["frames"][0].update(fl_x=-5.0), r"frames\[0\] does not give a valid camera"),
        (lambda m: m.update(timestep_indices=[0, 1]), r"'timestep_indices' lists \[0, 1\]"),
        (lambda m: m["frames"].append(m["frames"][0]), r"repeats timestep 0, camera 0"),
        (lambda m: m["frames"][0].update(w=41), r"00000_00\.png: is 40×30 but"),
    ],
)
def test_bad_transforms_are_named(subject_root, change, pattern):
    edit_json(subject_root / "transforms_train.json", change)
    with pytest.raises(DatasetError, match=r"transforms_train\.json|00000_00\.png") as info:
        load_subject(subject_root)
    assert info.match(pattern)


def test_corrupt_png_header_is_caught_at_load_time(subject_root):
    (subject_root / "images" / "00001_00.png").write_bytes(b"not a png at all, really not at all")
    with pytest.raises(DatasetError, match=r"images/00001_00\.png: not a PNG file"):
        load_subject(subject_root)


@pytest.mark.parametrize("split", ["train", "test"])
def test_a_corrupt_image_body_fails_at_open(subject_root, split):
    """A held-out frame is first decoded after training: a corrupt body must be found when
    the subject is opened, before any work."""
    name = json.loads((subject_root / f"transforms_{split}.json").read_text())["frames"][-1]
    path = subject_root / name["file_path"]
    path.write_bytes(path.read_bytes()[:60])  # header intact, pixel data cut
    with pytest.raises(DatasetError, match=re.escape(name["file_path"]) + ": could not be decoded"):
        load_subject(subject_root)


def test_a_gray_image_fails_at_open(subject_root):
    import cv2

    path = subject_root / "images" / "00001_00.png"
    cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    with pytest.raises(
        DatasetError, match=r"images/00001_00\.png: has 1 channels, expected 3 or 4"
    ):
        load_subject(subject_root)


def test_wrong_size_normal_map(subject_root):
    import cv2

    cv2.imwrite(str(subject_root / "normals" / "00002_00.png"), np.zeros((5, 5, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"normals/00002_00\.png: is 5×5"):
        load_subject(subject_root)


def test_normal_maps_for_only_some_frames(subject_root):
    (subject_root / "normals" / "00002_00.png").unlink()
    with pytest.raises(DatasetError, match="normal maps exist for some frames but not all"):
        load_subject(subject_root)


def test_flame_file_problems(subject_root):
    path = subject_root / "flame_param" / "00001.npz"
    path.write_bytes(b"garbage")
    with pytest.raises(DatasetError, match=r"00001\.npz: is not a readable \.npz"):
        load_subject(subject_root)
    params = random_flame(np.random.default_rng(0), num_verts=7)
    del params["jaw_pose"]
    np.savez(path, **params)
    with pytest.raises(DatasetError, match=r"00001\.npz: missing FLAME keys \['jaw_pose'\]"):
        load_subject(subject_root)
    params = random_flame(np.random.default_rng(0), num_verts=7)
    params["eyes_pose"] = np.zeros((1, 3), np.float32)
    np.savez(path, **params)
    with pytest.raises(DatasetError, match=r"'eyes_pose' must have shape \(1, 6\)"):
        load_subject(subject_root)
    params = random_flame(np.random.default_rng(0), num_verts=7)
    params["expr"] = np.zeros((1, 50), np.float32)  # a different count than the others
    np.savez(path, **params)
    with pytest.raises(DatasetError, match=r"00001\.npz: FLAME arrays differ from 00000\.npz"):
        load_subject(subject_root)
    params = random_flame(np.random.default_rng(0), num_verts=7)
    params["rotation"][0, 1] = np.nan
    np.savez(path, **params)
    with pytest.raises(DatasetError, match=r"'rotation' must hold finite floats"):
        load_subject(subject_root)


def test_bad_arguments(subject_root):
    with pytest.raises(ValueError, match="test_last must be a positive int"):
        load_subject(subject_root, test_last=0)
    with pytest.raises(DatasetError, match="too few to hold out the last 4"):
        load_subject(subject_root, test_last=4)
