"""Reading a subject in the VHAP / GaussianAvatars layout (see :mod:`urhead.data.layout`).

Everything is checked when the subject is opened: the JSON files and every key the reader
needs, every referenced image, mask and normal map (decoded whole once: size, bit depth,
channels, an intact body) and every FLAME parameter file (they are small and loaded
whole). The pixels are then decoded again when a frame is indexed, through a bounded LRU
cache shared by the splits.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from urhead._memory import available_memory_bytes
from urhead._threads import num_threads
from urhead.camera import Camera
from urhead.data.images import (
    check_png,
    exr_size,
    png_size,
    read_exr_rgb,
    read_png,
    read_png_uint8,
)
from urhead.data.layout import (
    CANONICAL_FLAME,
    FLAME_OPTIONAL_SHAPES,
    FLAME_SHAPES,
    FRAME_KEYS_REQUIRED,
    NORMALS_DIR,
    SPLIT_FILES,
    TOP_LEVEL_KEYS,
    TRANSFORMS,
    DatasetError,
    MissingFileError,
    check_flame_params,
    decode_float_normals,
    decode_normals,
)


@dataclass(frozen=True)
class Frame:
    """One decoded frame. Tensors are shared with the cache: treat them as read-only."""

    timestep: int
    """``timestep_index`` of the frame (position in the subject's timeline)."""
    camera_index: int
    image: torch.Tensor
    """(H, W, 3) float32 RGB in [0, 1], composited on the subject's background."""
    mask: torch.Tensor
    """(H, W) float32 foreground alpha in [0, 1]."""
    camera: Camera
    flame: dict
    """FLAME parameters as stored in the frame's npz (numpy arrays, shapes of FORMATS.md)."""
    normals: torch.Tensor | None
    """(H, W, 3) float32 unit normals in OpenCV camera axes (zero where undefined), or None
    when the subject has no normal maps."""
    image_path: Path


@dataclass(frozen=True)
class FrameRecord:
    """A frame as described by the transforms file, validated but not decoded."""

    timestep: int
    timestep_original: int
    camera_index: int
    camera: Camera
    image_path: Path
    mask_path: Path | None
    flame_path: Path
    normals_path: Path | None


class FrameSequence(Sequence):
    """The frames of one split, in file order. Indexing decodes (or reuses) a frame."""

    def __init__(self, name: str, records: list[FrameRecord], subject: Subject):
        self.name = name
        self.records = tuple(records)
        self._subject = subject

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        return self._subject._frame(self.records[index])

    @property
    def timesteps(self) -> list[int]:
        return [r.timestep for r in self.records]

    def flame_params(self) -> dict[str, np.ndarray]:
        """Every FLAME key stacked over the frames: ``{key: (N, ...)}`` (the leading 1 of
        per-timestep keys dropped, ``shape`` repeated per frame)."""
        per_frame = [self._subject.flame[r.flame_path] for r in self.records]
        if not per_frame:
            return {}
        keys = per_frame[0].keys()
        return {
            k: np.stack(
                [p[k][0] if p[k].ndim > 1 and p[k].shape[0] == 1 else p[k] for p in per_frame]
            )
            for k in keys
        }

    def __repr__(self) -> str:
        return f"FrameSequence({self.name!r}, {len(self)} frames)"


class Subject:
    """A dataset opened by :func:`load_subject`: ``train``, ``val`` and ``test`` sequences,
    the image size, the FLAME parameters of every timestep (``flame``, keyed by file) and
    ``canonical_flame`` when the subject has ``canonical_flame_param.npz``."""

    def __init__(
        self,
        root: Path,
        splits: dict[str, list[FrameRecord]],
        flame: dict[Path, dict],
        canonical_flame: dict | None,
        cache_size: int | None,
        cache_bytes: int,
    ):
        self.root = root
        self.flame = flame
        self.canonical_flame = canonical_flame
        self.train = FrameSequence("train", splits["train"], self)
        self.val = FrameSequence("val", splits["val"], self)
        self.test = FrameSequence("test", splits["test"], self)
        first = next(r for s in splits.values() for r in s)
        self.width, self.height = first.camera.width, first.camera.height
        self.has_normals = first.normals_path is not None
        self._cache: OrderedDict[Path, Frame] = OrderedDict()
        self._cache_size = cache_size
        self._cache_bytes = cache_bytes
        self._cached_bytes = 0
        self._lock = threading.Lock()

    def fingerprint(self) -> str:
        """SHA-256 (hex) of what a fit depends on besides the pixels: every split's
        timesteps, cameras and FLAME parameters. A checkpoint records it, so resuming with
        another subject (or another tracking of it) is recognised."""
        digest = hashlib.sha256()
        for split in (self.train, self.val, self.test):
            for r in split.records:
                digest.update(f"{split.name} {r.timestep} {r.camera_index}".encode())
                digest.update(r.camera.K.numpy().tobytes() + r.camera.viewmat.numpy().tobytes())
                digest.update(f"{r.camera.width}x{r.camera.height}".encode())
                for key, value in sorted(self.flame[r.flame_path].items()):
                    digest.update(key.encode() + np.ascontiguousarray(value).tobytes())
        return digest.hexdigest()

    def __repr__(self) -> str:
        return (
            f"Subject({str(self.root)!r}, {self.width}×{self.height}, train {len(self.train)}, "
            f"val {len(self.val)}, test {len(self.test)}, normals {self.has_normals})"
        )

    def _frame(self, record: FrameRecord) -> Frame:
        with self._lock:
            hit = self._cache.get(record.image_path)
            if hit is not None:
                self._cache.move_to_end(record.image_path)
                return hit
        frame = self._decode(record)
        with self._lock:
            if record.image_path not in self._cache:  # another thread may have decoded it
                self._cache[record.image_path] = frame
                self._cached_bytes += _frame_bytes(frame)
            while len(self._cache) > 1 and (
                self._cached_bytes > self._cache_bytes
                or (self._cache_size is not None and len(self._cache) > self._cache_size)
            ):
                _, dropped = self._cache.popitem(last=False)
                self._cached_bytes -= _frame_bytes(dropped)
        return frame

    def _decode(self, r: FrameRecord) -> Frame:
        h, w = r.camera.height, r.camera.width
        pixels = read_png(r.image_path)
        if pixels.ndim != 3 or pixels.shape[2] not in (3, 4) or pixels.shape[:2] != (h, w):
            raise DatasetError(
                r.image_path, f"must be an RGB(A) image of {w}×{h}, got {pixels.shape}"
            )
        if r.mask_path is None:
            if pixels.shape[2] != 4:
                raise DatasetError(r.image_path, "has no fg_mask_path and no alpha channel")
            mask = pixels[..., 3]
        else:
            mask = read_png(r.mask_path)
            if mask.ndim == 3:
                mask = mask[..., 0]
            if mask.shape != (h, w):
                raise DatasetError(r.mask_path, f"must be {w}×{h}, got {mask.shape}")
        normals = None
        if r.normals_path is not None:
            normals = torch.from_numpy(_read_normals(r.normals_path, h, w))
        return Frame(
            timestep=r.timestep,
            camera_index=r.camera_index,
            image=torch.from_numpy(np.ascontiguousarray(pixels[..., :3])),
            mask=torch.from_numpy(np.ascontiguousarray(mask)),
            camera=r.camera,
            flame=self.flame[r.flame_path],
            normals=normals,
            image_path=r.image_path,
        )


def load_subject(
    root: str | os.PathLike,
    test_last: int | None = None,
    cache_size: int | None = None,
    cache_bytes: int | None = None,
) -> Subject:
    """Open a subject in the VHAP / GaussianAvatars layout (FORMATS.md).

    Args:
        root: the subject folder (with ``transforms*.json``, ``images/``, ``fg_masks/``,
            ``flame_param/``, optionally ``normals/``).
        test_last: None to take the splits from ``transforms_{train,val,test}.json``
            as VHAP's exporter writes them: monocular, ``val`` is empty (its file lists
            the training timesteps but no frames); multi-view, ``val`` is one held-out
            camera over the training timesteps and ``test`` every camera over the later
            timesteps. N > 0 to split ``transforms.json`` by time instead: the last N
            timesteps are the test set, the rest the training set, ``val`` is empty (the
            benchmark protocol of the paper family, N = 350).
        cache_size: at most this many decoded frames are kept (LRU); None: no count limit.
        cache_bytes: and at most this many bytes of them (default: a quarter of the
            memory available, at most 8 GiB). A fit visits its training frames in a new
            order every epoch and an evaluation scans the held-out frames in order, so a
            cache smaller than the frames misses on nearly every read; at 512² a frame
            with normals is ~7 MB, so the built-in subject's 300 fit in ~2.2 GB and each
            frame is decoded once instead of on nearly every visit (~30 ms each).

    Cameras come from each frame's OpenGL camera-to-world ``transform_matrix`` and its
    ``fl_x, fl_y, cx, cy, w, h`` (the top-level values when a frame has none), converted to
    OpenCV world-to-camera. A split file with frames must list exactly their timesteps and
    cameras in ``timestep_indices`` / ``camera_indices``; a split without frames is taken
    whatever it lists; no ``val`` or ``test`` frame may also be a training frame. Raises
    :class:`~urhead.data.DatasetError` (a ``ValueError``; :class:`~urhead.data.MissingFileError`
    is also a ``FileNotFoundError``) naming the file at fault.
    """
    root = Path(root)
    if not root.is_dir():
        raise MissingFileError(root, "subject folder not found")
    if cache_size is not None and cache_size < 1:
        raise ValueError(f"cache_size must be >= 1 or None, got {cache_size}")
    if cache_bytes is None:
        cache_bytes = default_cache_bytes()
    elif cache_bytes < 0:
        raise ValueError(f"cache_bytes must be >= 0, got {cache_bytes}")
    cameras: dict[tuple, Camera] = {}
    if test_last is None:
        for split in ("train", "test"):
            if not (root / SPLIT_FILES[split]).is_file():
                raise MissingFileError(
                    root / SPLIT_FILES[split],
                    "split file not found (pass test_last=N to split transforms.json by time)",
                )
        splits = {
            name: _read_transforms(root, root / file, cameras) if (root / file).is_file() else []
            for name, file in SPLIT_FILES.items()
        }
        _check_held_out(root, splits)
    else:
        if isinstance(test_last, bool) or not isinstance(test_last, int) or test_last < 1:
            raise ValueError(f"test_last must be a positive int or None, got {test_last!r}")
        everything = _read_transforms(root, root / TRANSFORMS, cameras)
        timesteps = sorted({r.timestep for r in everything})
        if test_last >= len(timesteps):
            raise DatasetError(
                root / TRANSFORMS,
                f"has {len(timesteps)} timesteps, too few to hold out the last {test_last}",
            )
        first_test = timesteps[len(timesteps) - test_last]
        splits = {
            "train": [r for r in everything if r.timestep < first_test],
            "val": [],
            "test": [r for r in everything if r.timestep >= first_test],
        }
    if not any(splits.values()):
        raise DatasetError(root, "the transforms files list no frames")
    sizes = {(r.camera.width, r.camera.height) for s in splits.values() for r in s}
    if len(sizes) > 1:
        raise DatasetError(root, f"frames have different image sizes {sorted(sizes)}")
    with_normals = {r.normals_path is not None for s in splits.values() for r in s}
    if len(with_normals) > 1:
        raise DatasetError(root / NORMALS_DIR, "normal maps exist for some frames but not all")
    flame = _read_all_flame(sorted({r.flame_path for s in splits.values() for r in s}))
    _decode_all(splits)
    canonical = None
    if (root / CANONICAL_FLAME).is_file():
        canonical = _read_flame(root / CANONICAL_FLAME)
    return Subject(root, splits, flame, canonical, cache_size, cache_bytes)


def default_cache_bytes() -> int:
    """The decoded-frame cache's default budget: a quarter of the memory available now
    (MemAvailable, lowered to the cgroup's limit), at most 8 GiB; 1 GiB where neither is
    known."""
    available = available_memory_bytes()
    if available is None:
        return 1 << 30
    return min(available // 4, 8 << 30)


def _frame_bytes(frame: Frame) -> int:
    tensors = (frame.image, frame.mask, frame.normals)
    return sum(t.numel() * t.element_size() for t in tensors if t is not None)


def _read_transforms(root: Path, path: Path, cameras: dict) -> list[FrameRecord]:
    if not path.is_file():
        raise MissingFileError(path, "file not found")
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(path, f"is not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise DatasetError(path, "must hold a JSON object")
    missing = [k for k in TOP_LEVEL_KEYS if k not in meta]
    if missing:
        raise DatasetError(path, f"missing top-level keys {missing}")
    if not isinstance(meta["frames"], list):
        raise DatasetError(path, "'frames' must be a list")
    listed = {key: _index_list(path, meta, key) for key in ("timestep_indices", "camera_indices")}
    records, seen = [], set()
    for i, frame in enumerate(meta["frames"]):
        r = _frame_record(root, path, i, frame, meta, cameras)
        key = (r.timestep, r.camera_index)
        if key in seen:
            raise DatasetError(path, f"frames[{i}] repeats timestep {key[0]}, camera {key[1]}")
        seen.add(key)
        records.append(r)
    # A split without frames has nothing to check its lists against: VHAP's monocular
    # export writes val as "frames": [], "camera_indices": [] and the *training*
    # timesteps, and an empty test split still lists the cameras.
    if records:
        for key, used in (
            ("timestep_indices", sorted({r.timestep for r in records})),
            ("camera_indices", sorted({r.camera_index for r in records})),
        ):
            if sorted(listed[key]) != used:
                raise DatasetError(
                    path,
                    f"'{key}' lists {_summary(sorted(listed[key]))} but the frames use "
                    f"{_summary(used)}; a split file with frames must list exactly the "
                    "timesteps and cameras of its frames (as VHAP's exporter writes them)",
                )
    return records


def _index_list(path: Path, meta: dict, key: str) -> list[int]:
    values = meta[key]
    ok = isinstance(values, list) and all(
        isinstance(v, int) and not isinstance(v, bool) for v in values
    )
    if not ok or len(set(values)) != len(values):
        raise DatasetError(
            path, f"'{key}' must be a list of distinct integers, got {_summary(values)}"
        )
    return values


def _check_held_out(root: Path, splits: dict[str, list[FrameRecord]]) -> None:
    """No frame (timestep, camera) of a held-out split may be a training frame."""
    trained = {(r.timestep, r.camera_index) for r in splits["train"]}
    for name in ("val", "test"):
        both = sorted(trained & {(r.timestep, r.camera_index) for r in splits[name]})
        if both:
            t, c = both[0]
            raise DatasetError(
                root / SPLIT_FILES[name],
                f"{len(both)} of its frames are also in {SPLIT_FILES['train']} (first: "
                f"timestep {t}, camera {c}); a held-out frame must not be trained on",
            )


def _frame_record(root, path, i, frame, meta, cameras) -> FrameRecord:
    where = f"frames[{i}]"
    if not isinstance(frame, dict):
        raise DatasetError(path, f"{where} must be a JSON object")
    missing = [k for k in FRAME_KEYS_REQUIRED if k not in frame]
    if missing:
        raise DatasetError(path, f"{where} is missing keys {missing}")

    def number(key, kind=float):
        value = frame.get(key, meta.get(key))
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not ok or not math.isfinite(value) or (kind is int and value != int(value)):
            raise DatasetError(
                path, f"{where}.{key} must be a finite {kind.__name__}, got {value!r}"
            )
        return kind(value)

    timestep = number("timestep_index", int)
    camera_index = number("camera_index", int) if "camera_index" in frame else 0
    width, height = number("w", int), number("h", int)
    intrinsics = tuple(number(k) for k in ("fl_x", "fl_y", "cx", "cy"))
    c2w = np.asarray(frame["transform_matrix"], dtype=object)
    if c2w.shape != (4, 4):
        raise DatasetError(path, f"{where}.transform_matrix must be 4×4, got shape {c2w.shape}")
    try:
        c2w = c2w.astype(np.float64)
    except (TypeError, ValueError):
        raise DatasetError(path, f"{where}.transform_matrix must hold numbers") from None
    if not np.all(np.isfinite(c2w)):
        raise DatasetError(path, f"{where}.transform_matrix must be finite")
    rotation = c2w[:3, :3]
    # A camera pose is rigid: a scaled or sheared matrix would move every pixel's ray.
    rigid = np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-4) and np.linalg.det(rotation) > 0
    if not rigid or not np.allclose(c2w[3], (0, 0, 0, 1), atol=1e-6):
        raise DatasetError(
            path,
            f"{where}.transform_matrix is not a rigid camera pose (its 3×3 part must be a "
            "rotation and its last row 0 0 0 1)",
        )
    key = (c2w.tobytes(), intrinsics, width, height)
    if key not in cameras:
        try:
            cameras[key] = Camera.from_opengl_c2w(c2w, *intrinsics, width, height)
        except (ValueError, TypeError) as e:
            raise DatasetError(path, f"{where} does not give a valid camera: {e}") from None
    camera = cameras[key]

    def file(key, suffix=".png") -> Path:
        value = frame[key]
        if not isinstance(value, str) or not value:
            raise DatasetError(path, f"{where}.{key} must be a relative path, got {value!r}")
        p = root / value
        return p if p.suffix else p.with_suffix(suffix)

    image_path = file("file_path")
    mask_path = file("fg_mask_path") if "fg_mask_path" in frame else None
    flame_path = file("flame_param_path", ".npz")
    if not flame_path.is_file():
        raise MissingFileError(
            flame_path, f"not found (flame_param_path of {where} in {path.name})"
        )
    # The image's alpha is the mask when there is no mask file.
    image_channels = (3, 4) if mask_path is not None else (4,)
    _check_png(image_path, width, height, image_channels, f"file_path of {where} in {path.name}")
    if mask_path is not None:
        _check_png(mask_path, width, height, (1, 3, 4), f"fg_mask_path of {where} in {path.name}")
    normals_path = root / NORMALS_DIR / (image_path.stem + ".png")
    if normals_path.is_file():
        _check_png(normals_path, width, height, (3,), f"normal map of {where} in {path.name}")
    elif normals_path.with_suffix(".exr").is_file():
        normals_path = normals_path.with_suffix(".exr")
        size = exr_size(normals_path)
        if size != (width, height):
            raise DatasetError(
                normals_path, f"is {size[0]}×{size[1]} but the transforms say {width}×{height}"
            )
    else:
        normals_path = None
    original = frame.get("timestep_index_original", timestep)
    return FrameRecord(
        timestep=timestep,
        timestep_original=int(original) if isinstance(original, (int, float)) else timestep,
        camera_index=camera_index,
        camera=camera,
        image_path=image_path,
        mask_path=mask_path,
        flame_path=flame_path,
        normals_path=normals_path,
    )


def _check_png(p: Path, width: int, height: int, channels: tuple[int, ...], what: str) -> None:
    """The header's size (cheap, the clearer message); the whole file is decoded later,
    with every other, by :func:`_decode_all`."""
    if not p.is_file():
        raise MissingFileError(p, f"not found ({what})")
    size = png_size(p)
    if size != (width, height):
        raise DatasetError(p, f"is {size[0]}×{size[1]} but the transforms say {width}×{height}")


def _decode_all(splits: dict[str, list[FrameRecord]]) -> None:
    """Decodes every image, mask and PNG normal map whole and checks its size, bit depth
    and channels, so a corrupt body is found at open, not when the frame is first used
    (after training, for a held-out frame). Spread over urhead's threads (OpenCV's
    decoder releases the GIL); the first failure in file order is raised."""
    checks = []
    for records in splits.values():
        for r in records:
            size = (r.camera.width, r.camera.height)
            with_mask = r.mask_path is not None
            checks.append((r.image_path, *size, (3, 4) if with_mask else (4,)))
            if with_mask:
                checks.append((r.mask_path, *size, (1, 3, 4)))
            if r.normals_path is not None and r.normals_path.suffix == ".png":
                checks.append((r.normals_path, *size, (3,)))
    pool = ThreadPoolExecutor(max_workers=min(num_threads(), len(checks) or 1))
    try:
        for _ in pool.map(lambda check: check_png(*check), checks):
            pass
    finally:
        pool.shutdown(cancel_futures=True)


def _read_flame(path: Path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            params = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise MissingFileError(path, "file not found") from None
    except Exception as e:  # zipfile, pickle and format errors all mean a corrupt file
        raise DatasetError(path, f"is not a readable .npz file ({type(e).__name__}: {e})") from None
    check_flame_params(params, path)
    return params


def _read_all_flame(paths: list[Path]) -> dict[Path, dict]:
    out, sizes, first = {}, {}, None
    for p in paths:
        params = _read_flame(p)
        shape_of = {
            k: v.shape for k, v in params.items() if k in FLAME_SHAPES or k in FLAME_OPTIONAL_SHAPES
        }
        if first is None:
            first, sizes = p, shape_of
        elif shape_of != sizes:
            diff = {k: (sizes.get(k), shape_of.get(k)) for k in set(sizes) | set(shape_of)}
            diff = {k: v for k, v in diff.items() if v[0] != v[1]}
            raise DatasetError(p, f"FLAME arrays differ from {first.name}: {diff}")
        out[p] = params
    return out


def _read_normals(path: Path, h: int, w: int) -> np.ndarray:
    if path.suffix == ".exr":
        return decode_float_normals(read_exr_rgb(path))
    rgb = read_png_uint8(path)
    if rgb.shape != (h, w, 3):
        raise DatasetError(path, f"must be an RGB image of {w}×{h}, got {rgb.shape}")
    return decode_normals(rgb)


def _summary(values) -> str:
    if not isinstance(values, list):
        return repr(values)
    return repr(values) if len(values) <= 6 else f"[{values[0]}, …, {values[-1]}] ({len(values)})"
