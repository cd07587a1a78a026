"""Normal maps stored as EXR (float OpenGL-axes normals, as normal estimators write them)
read like the PNG ones, at float precision; a wrong size or a broken file is an error
naming it."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from test_data_io import H, W, write_subject
from urhead.data import DatasetError, load_subject


def write_exr_normals(path, opencv_normals, half=False):
    gl = opencv_normals * np.array([1.0, -1.0, -1.0], np.float32)  # stored in OpenGL axes
    dtype = np.float16 if half else np.float32
    channels = {c: np.ascontiguousarray(gl[..., i], dtype) for i, c in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def png_to_exr_normals(root, written, half=False):
    """Replaces every PNG normal map of the subject by an EXR of the true normals."""
    for png in sorted((root / "normals").glob("*.png")):
        timestep = int(png.stem.split("_")[0])
        write_exr_normals(png.with_suffix(".exr"), written[timestep][3], half)
        png.unlink()


@pytest.mark.parametrize("half", [False, True])
def test_exr_normal_maps_read_at_float_precision(tmp_path, half):
    root = tmp_path / "subject"
    written = write_subject(root, num_frames=4)
    png_to_exr_normals(root, written, half)
    subject = load_subject(root)
    assert subject.has_normals
    for frame in subject.train:
        truth = written[frame.timestep][3]
        got = frame.normals.numpy()
        defined = np.any(truth != 0, axis=-1)
        assert np.array_equal(np.any(got != 0, axis=-1), defined)
        # half floats: ~1e-3 per component; float: exact up to the renormalisation
        assert np.abs(got[defined] - truth[defined]).max() < (2e-3 if half else 1e-6)


def test_exr_normal_map_of_the_wrong_size_names_the_file(tmp_path):
    root = tmp_path / "subject"
    written = write_subject(root, num_frames=4)
    png_to_exr_normals(root, written)
    bad = sorted((root / "normals").glob("*.exr"))[1]
    write_exr_normals(bad, np.zeros((H + 1, W, 3), np.float32))
    with pytest.raises(DatasetError, match=rf"{bad.name}.*{W}×{H + 1}"):
        load_subject(root)
    bad.write_bytes(b"not an exr")
    with pytest.raises(DatasetError, match=rf"{bad.name}.*not a readable EXR"):
        load_subject(root)
