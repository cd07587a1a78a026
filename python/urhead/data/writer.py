"""Writing a subject in the VHAP / GaussianAvatars layout, atomically: everything goes into
a hidden temporary folder beside the target, which is renamed into place only when the
subject is complete, so a reader never sees a half-written subject."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np

from urhead._atomic import commit_folder, temporary_folder
from urhead.camera import Camera
from urhead.data.images import to_uint8, write_png
from urhead.data.layout import (
    CANONICAL_FLAME,
    FLAME_DIR,
    IMAGES_DIR,
    MASKS_DIR,
    NORMALS_DIR,
    SPLIT_FILES,
    TRANSFORMS,
    canonical_flame_params,
    check_flame_params,
    encode_normals,
    flame_file,
    frame_stem,
)


def opengl_c2w(camera: Camera) -> np.ndarray:
    """(4, 4) camera-to-world in OpenGL axes (x right, y up, z back) of an OpenCV camera:
    the inverse of :meth:`urhead.Camera.from_opengl_c2w`."""
    c2w = np.linalg.inv(camera.viewmat.double().numpy())
    c2w[:3, 1:3] *= -1
    c2w[3] = (0.0, 0.0, 0.0, 1.0)
    return c2w


class SubjectWriter:
    """Writes frames of one fixed camera, then the transforms files on :meth:`finish`.

    Use as a context manager: leaving the block normally finishes the subject, an
    exception discards everything written so far::

        with SubjectWriter(out, camera) as w:
            for t in range(n):
                w.add_frame(t, image, mask, flame, normals=normals)

    Args:
        root: the subject folder to create.
        camera: the fixed camera (an :class:`urhead.Camera`).
        overwrite: replace an existing ``root`` (only once the new subject is complete).
        test_last: timesteps held out as the test split; None: VHAP's split, the first
            ceil(0.7·T) timesteps train, the rest test. Either way the split files are laid
            out as VHAP's exporter writes them for one camera (:func:`vhap_split_files`):
            ``val`` has no frames.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        camera: Camera,
        *,
        overwrite: bool = False,
        test_last: int | None = None,
    ):
        self.root = Path(root)
        if self.root.exists() and not overwrite:
            raise FileExistsError(f"{self.root}: already exists (pass overwrite=True to replace)")
        if test_last is not None and (not isinstance(test_last, int) or test_last < 1):
            raise ValueError(f"test_last must be a positive int or None, got {test_last!r}")
        self.camera = camera
        self.overwrite = overwrite
        self.test_last = test_last
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = temporary_folder(self.root)
        for sub in (IMAGES_DIR, MASKS_DIR, FLAME_DIR):
            (self._tmp / sub).mkdir(parents=True)
        self._frames: list[dict] = []
        self._flame_shapes: dict | None = None
        self._with_normals: bool | None = None
        self._done = False

    @property
    def staging(self) -> Path:
        """The temporary folder being filled: extra files written here move into place
        with the subject."""
        return self._tmp

    def __enter__(self) -> SubjectWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and not self._done:
            self.finish()
        else:
            self.abort()

    def add_frame(
        self,
        timestep: int,
        image: np.ndarray,
        mask: np.ndarray,
        flame: dict,
        normals: np.ndarray | None = None,
    ) -> None:
        """Write one timestep.

        Args:
            timestep: its index; timesteps must be added in increasing order.
            image: (H, W, 3) RGB in [0, 1] (float) or uint8, already composited on the
                background.
            mask: (H, W) foreground alpha in [0, 1] (float) or uint8.
            flame: FLAME parameters with the keys and shapes of FORMATS.md.
            normals: (H, W, 3) unit normals in OpenCV camera axes, zero where undefined;
                give them for every frame or for none.
        """
        if self._done:
            raise RuntimeError("the subject is already finished")
        h, w = self.camera.height, self.camera.width
        if self._frames and timestep <= self._frames[-1]["timestep_index"]:
            raise ValueError(f"timestep {timestep} must exceed the previous one")
        image, mask = np.asarray(image), np.asarray(mask)
        if image.shape != (h, w, 3):
            raise ValueError(f"image must be ({h}, {w}, 3), got {image.shape}")
        if mask.shape != (h, w):
            raise ValueError(f"mask must be ({h}, {w}), got {mask.shape}")
        if self._frames and (normals is not None) != self._with_normals:
            raise ValueError("normals must be given for every frame or for none")
        self._with_normals = normals is not None
        flame = dict(flame)
        check_flame_params(flame, flame_file(timestep))
        shapes = {k: v.shape for k, v in flame.items()}
        if self._flame_shapes is None:
            self._flame_shapes = shapes
        elif shapes != self._flame_shapes:
            raise ValueError(f"flame shapes {shapes} differ from the first frame's")

        stem = frame_stem(timestep, 0)
        write_png(self._tmp / IMAGES_DIR / f"{stem}.png", _as_uint8(image))
        write_png(self._tmp / MASKS_DIR / f"{stem}.png", _as_uint8(mask))
        if normals is not None:
            normals = np.asarray(normals, np.float32)
            if normals.shape != (h, w, 3):
                raise ValueError(f"normals must be ({h}, {w}, 3), got {normals.shape}")
            (self._tmp / NORMALS_DIR).mkdir(exist_ok=True)
            write_png(self._tmp / NORMALS_DIR / f"{stem}.png", encode_normals(normals))
        np.savez(self._tmp / flame_file(timestep), **flame)
        self._frames.append(self._frame_entry(timestep, stem))

    def finish(self) -> Path:
        """Write the transforms files and the canonical parameters, then move the subject
        into place. Returns the subject folder."""
        if self._done:
            return self.root
        if not self._frames:
            self.abort()
            raise ValueError("a subject needs at least one frame")
        shapes = self._flame_shapes
        static = shapes.get("static_offset")
        canonical = canonical_flame_params(
            shapes["shape"][0], shapes["expr"][1], None if static is None else static[1]
        )
        np.savez(self._tmp / CANONICAL_FLAME, **canonical)
        num = len(self._frames)
        if self.test_last is not None and self.test_last >= num:
            self.abort()
            raise ValueError(f"test_last={self.test_last} leaves no training frames out of {num}")
        num_train = num - self.test_last if self.test_last is not None else vhap_train_count(num)
        for name, meta in vhap_split_files(self._frames, num_train, self._intrinsics()).items():
            (self._tmp / name).write_text(json.dumps(meta, indent=4))
        commit_folder(self._tmp, self.root)
        self._done = True
        return self.root

    def abort(self) -> None:
        """Discard everything written (the target folder is left untouched)."""
        shutil.rmtree(self._tmp, ignore_errors=True)
        self._done = True

    def _intrinsics(self) -> dict:
        c = self.camera
        return {
            "cx": c.cx,
            "cy": c.cy,
            "fl_x": c.fx,
            "fl_y": c.fy,
            "h": c.height,
            "w": c.width,
            "camera_angle_x": 2 * math.atan(c.width / (2 * c.fx)),
            "camera_angle_y": 2 * math.atan(c.height / (2 * c.fy)),
        }

    def _frame_entry(self, timestep: int, stem: str) -> dict:
        entry = {
            "timestep_index": timestep,
            "timestep_index_original": timestep,
            "timestep_id": f"frame_{timestep:05d}",
            "camera_index": 0,
            "camera_id": "00",
            **self._intrinsics(),
            "transform_matrix": opengl_c2w(self.camera).tolist(),
            "file_path": f"{IMAGES_DIR}/{stem}.png",
            "fg_mask_path": f"{MASKS_DIR}/{stem}.png",
            "flame_param_path": flame_file(timestep),
        }
        return entry


def vhap_train_count(num_timesteps: int) -> int:
    """Training timesteps of VHAP's split: the first ceil(0.7·T) (computed as VHAP does)."""
    return math.ceil(num_timesteps * 0.7)


def vhap_split_files(frames: list[dict], num_train: int, intrinsics: dict) -> dict[str, dict]:
    """The transforms files of a one-camera subject as VHAP's exporter writes them, by
    file name: ``transforms.json`` and its two backups list every frame (the first backup
    is written before the FLAME parameters, so its frames have no ``flame_param_path``);
    train holds the first ``num_train`` timesteps, test the rest; val is empty but names
    the training timesteps (VHAP holds out a camera as val, and one camera leaves none).
    Each file copies the top-level intrinsics and lists its own timesteps and cameras."""
    timesteps = [f["timestep_index"] for f in frames]
    cameras = sorted({f["camera_index"] for f in frames})

    def transforms(split_frames, split_timesteps, split_cameras):
        return {
            **intrinsics,
            "frames": split_frames,
            "timestep_indices": split_timesteps,
            "camera_indices": split_cameras,
        }

    without_flame = [{k: v for k, v in f.items() if k != "flame_param_path"} for f in frames]
    return {
        TRANSFORMS: transforms(frames, timesteps, cameras),
        "transforms_backup.json": transforms(without_flame, timesteps, cameras),
        "transforms_backup_flame.json": transforms(frames, timesteps, cameras),
        SPLIT_FILES["train"]: transforms(frames[:num_train], timesteps[:num_train], cameras),
        SPLIT_FILES["val"]: transforms([], timesteps[:num_train], []),
        SPLIT_FILES["test"]: transforms(frames[num_train:], timesteps[num_train:], cameras),
    }


def _as_uint8(values: np.ndarray) -> np.ndarray:
    return values if values.dtype == np.uint8 else to_uint8(values)
