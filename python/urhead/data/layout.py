"""The VHAP / GaussianAvatars monocular dataset layout (FORMATS.md), shared by the reader
and the writer: file names, JSON keys, the FLAME parameter table and the normal-map
encoding.

::

    <subject>/images/{t:05d}_{c:02d}.png       RGB composited on the background colour
    <subject>/fg_masks/{t:05d}_{c:02d}.png     uint8 alpha
    <subject>/flame_param/{t:05d}.npz          one per timestep
    <subject>/canonical_flame_param.npz        zeros except jaw_pose = [[0.3, 0, 0]]
    <subject>/transforms{,_train,_val,_test}.json
    <subject>/normals/{t:05d}_{c:02d}.png      optional ground-truth normals
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

IMAGES_DIR = "images"
MASKS_DIR = "fg_masks"
FLAME_DIR = "flame_param"
NORMALS_DIR = "normals"
CANONICAL_FLAME = "canonical_flame_param.npz"
TRANSFORMS = "transforms.json"
SPLIT_FILES = {
    "train": "transforms_train.json",
    "val": "transforms_val.json",
    "test": "transforms_test.json",
}

TOP_LEVEL_KEYS = (
    "frames",
    "cx",
    "cy",
    "fl_x",
    "fl_y",
    "h",
    "w",
    "camera_angle_x",
    "camera_angle_y",
    "timestep_indices",
    "camera_indices",
)
"""Keys every transforms file has at its top level (the first camera's intrinsics)."""

FRAME_KEYS = (
    "timestep_index",
    "timestep_index_original",
    "timestep_id",
    "camera_index",
    "camera_id",
    "cx",
    "cy",
    "fl_x",
    "fl_y",
    "h",
    "w",
    "camera_angle_x",
    "camera_angle_y",
    "transform_matrix",
    "file_path",
    "fg_mask_path",
    "flame_param_path",
)
"""Keys the writer puts in every frame."""

FRAME_KEYS_REQUIRED = ("timestep_index", "transform_matrix", "file_path", "flame_param_path")
"""Keys the reader cannot do without; intrinsics fall back to the top level, the camera
index to 0 and the mask to the image's alpha channel."""

FLAME_SHAPES = {
    "translation": (1, 3),
    "rotation": (1, 3),
    "neck_pose": (1, 3),
    "jaw_pose": (1, 3),
    "eyes_pose": (1, 6),
    "shape": (None,),
    "expr": (1, None),
}
"""Required per-timestep FLAME keys and shapes (None: any size, the same in every file)."""

FLAME_OPTIONAL_SHAPES = {"static_offset": (1, None, 3), "dynamic_offset": (1, None, 3)}


class DatasetError(ValueError):
    """A dataset file is missing, corrupt or inconsistent. ``path`` names the file."""

    def __init__(self, path: str | os.PathLike, message: str):
        self.path = Path(path)
        super().__init__(f"{self.path}: {message}")


class MissingFileError(DatasetError, FileNotFoundError):
    """A file the dataset refers to does not exist."""


def frame_stem(timestep: int, camera: int) -> str:
    """``00012_00`` for timestep 12, camera 0."""
    return f"{timestep:05d}_{camera:02d}"


def flame_file(timestep: int) -> str:
    return f"{FLAME_DIR}/{timestep:05d}.npz"


def canonical_flame_params(num_shape: int, num_expr: int, num_vertices: int | None = None):
    """The canonical FLAME parameters VHAP writes (zeros, jaw slightly open)."""
    params = {
        "translation": np.zeros((1, 3), np.float32),
        "rotation": np.zeros((1, 3), np.float32),
        "neck_pose": np.zeros((1, 3), np.float32),
        "jaw_pose": np.array([[0.3, 0.0, 0.0]], np.float32),
        "eyes_pose": np.zeros((1, 6), np.float32),
        "shape": np.zeros((num_shape,), np.float32),
        "expr": np.zeros((1, num_expr), np.float32),
    }
    if num_vertices is not None:
        params["static_offset"] = np.zeros((1, num_vertices, 3), np.float32)
    return params


# Normal maps: camera-space unit normals in OpenCV axes (x right, y down, z forward; a
# surface facing the camera has z < 0) are stored as 8-bit RGB of the OpenGL-axes normal
# (x, -y, -z) mapped from [-1, 1] to [0, 255], the usual "blue faces the viewer" picture.
# Pixels without a normal are stored as (0, 0, 0), which no unit normal encodes to (it
# would need every component ≤ −0.996).


def encode_normals(normals: np.ndarray) -> np.ndarray:
    """(H, W, 3) OpenCV camera-space unit normals, zero where undefined → (H, W, 3) uint8."""
    valid = np.any(normals != 0, axis=-1, keepdims=True)
    gl = normals * np.array([1.0, -1.0, -1.0], np.float32)
    rgb = np.clip(np.rint((gl + 1.0) * 127.5), 0, 255).astype(np.uint8)
    return np.where(valid, rgb, 0).astype(np.uint8)


# Each channel's byte → its OpenCV-axes component before normalising: (3, 256) float32,
# the same float32 arithmetic as decoding the bytes one by one.
_NORMAL_BYTES = (np.arange(256, dtype=np.float32) / np.float32(127.5) - np.float32(1.0))[
    None
] * np.array([[1.0], [-1.0], [-1.0]], np.float32)


def decode_normals(rgb: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_normals`: (H, W, 3) uint8 → (H, W, 3) float32 unit normals
    in OpenCV camera axes, zero where undefined.

    A fit decodes a frame's normals every iteration, so this avoids numpy's slow paths
    (a reduction over a 3-long last axis, float temporaries of the whole map): a byte
    table per channel, then the norm summed in :func:`numpy.linalg.norm`'s order: the same
    bits as ``bytes / 127.5 − 1``, the axis flips and ``n / max(‖n‖, 1e-6)`` in float32."""
    valid = (rgb[..., 0] | rgb[..., 1] | rgb[..., 2]) != 0
    n = np.stack([_NORMAL_BYTES[k].take(rgb[..., k]) for k in range(3)], -1)
    squares = n * n
    norm = np.sqrt((squares[..., 0] + squares[..., 1]) + squares[..., 2])
    n /= np.maximum(norm, np.float32(1e-6))[..., None]
    np.copyto(n, np.float32(0.0), where=~valid[..., None])
    return n


def decode_float_normals(gl: np.ndarray) -> np.ndarray:
    """Float normal maps (EXR): (H, W, 3) OpenGL-axes normals (x, −y, −z) stored as they
    are, in [−1, 1] → (H, W, 3) float32 unit normals in OpenCV camera axes; (0, 0, 0) and
    non-finite pixels mark pixels without a normal."""
    gl = np.asarray(gl, np.float32)
    valid = np.all(np.isfinite(gl), axis=-1, keepdims=True) & np.any(
        gl != 0, axis=-1, keepdims=True
    )
    return _opengl_to_opencv(np.where(valid, gl, 0.0), valid)


def _opengl_to_opencv(gl: np.ndarray, valid: np.ndarray) -> np.ndarray:
    n = gl * np.array([1.0, -1.0, -1.0], np.float32)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    n = n / np.maximum(norm, 1e-6)
    return np.where(valid, n, 0.0).astype(np.float32)


def check_flame_params(params: dict, path: str | os.PathLike) -> None:
    """Check the keys and shapes of one timestep's FLAME parameters (converting them to
    float32 in place), raising :class:`DatasetError` naming ``path``."""
    missing = [k for k in FLAME_SHAPES if k not in params]
    if missing:
        raise DatasetError(path, f"missing FLAME keys {missing}")
    for key, want in (*FLAME_SHAPES.items(), *FLAME_OPTIONAL_SHAPES.items()):
        if key not in params:
            continue
        a = np.asarray(params[key])
        ok = a.ndim == len(want) and all(
            w is None or w == d for w, d in zip(want, a.shape, strict=True)
        )
        if not ok:
            shown = "(" + ", ".join("N" if w is None else str(w) for w in want) + ")"
            raise DatasetError(path, f"'{key}' must have shape {shown}, got {a.shape}")
        if a.dtype.kind != "f" or not np.all(np.isfinite(a)):
            raise DatasetError(path, f"'{key}' must hold finite floats")
        params[key] = a.astype(np.float32, copy=False)
