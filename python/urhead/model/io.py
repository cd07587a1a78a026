"""The avatar directory (FORMATS.md "Avatar directory"), self-contained so render, eval,
export and reenactment need no training data:

```
avatar.json     format version, map layout and resolution, counts, background, config
maps.npy        (H, R, channels) float32 UV maps, layout in avatar.json (H = map_rows, R
                but for a head whose atlas is a window of rows)
gaussians.npz   uv (N, 2), face (N,), bary (N, 3)
frames.npz      timesteps (T,), params (T, E + 18) = expr | pose (15) | translation,
                shape (S,), static_offset (V, 3) when the subject had one
head.npz        the head model the FLAME parameters refer to (urhead head format)
```

Directories are written under a temporary name and renamed into place, so a reader sees
the old avatar or the new one, never half of one.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from urhead import hugepages
from urhead._atomic import write_bytes_atomically, write_directory_atomically
from urhead.errors import InvalidArgumentError, NonFiniteError, ShapeError, reading
from urhead.head import head_fingerprint, load_head, save_head
from urhead.model.avatar import POSE_SIZE, Avatar
from urhead.model.map_layout import MapLayout

AVATAR_FORMAT = 1


def write_avatar_files(avatar: Avatar, folder: Path, extra: dict | None = None) -> None:
    """Writes the avatar's files into an existing folder (no atomicity; see
    :func:`save_avatar`)."""
    layout = avatar.layout
    meta = {
        "format": "urhead-avatar",
        "format_version": AVATAR_FORMAT,
        "sh_degree": layout.sh_degree,
        "gaussians": layout.gaussians,
        "offsets": layout.offsets,
        "shading": layout.shading,
        "resolution": avatar.resolution,
        "map_rows": int(avatar.maps.shape[0]),
        "channels": layout.channels,
        "num_gaussians": avatar.num_gaussians,
        "num_expr": avatar.num_expr,
        "num_frames": int(avatar.timesteps.shape[0]),
        "background": avatar.background.tolist(),
        "depth_eps": avatar.depth_eps,
        "head_sha256": head_fingerprint(avatar.head),
        **(extra or {}),
    }
    (folder / "avatar.json").write_text(json.dumps(meta, indent=2))
    np.save(folder / "maps.npy", avatar.maps.detach().numpy())
    np.savez(
        folder / "gaussians.npz",
        uv=avatar.gaussian_uv.numpy(),
        face=avatar.gaussian_face.numpy(),
        bary=avatar.gaussian_bary.numpy(),
    )
    frames = {
        "timesteps": avatar.timesteps.numpy(),
        "params": avatar.frame_params.detach().numpy(),
        "shape": avatar.shape.numpy(),
    }
    if avatar.static_offset is not None:
        frames["static_offset"] = avatar.static_offset.numpy()
    np.savez(folder / "frames.npz", **frames)
    save_head(avatar.head, folder / "head.npz")


def save_avatar(avatar: Avatar, path: str | os.PathLike, extra: dict | None = None) -> Path:
    """Writes the avatar directory at ``path`` atomically; ``extra`` goes into
    ``avatar.json`` (the config, for instance). Returns the path."""
    path = Path(path)
    write_directory_atomically(path, lambda tmp: write_avatar_files(avatar, tmp, extra))
    return path


AVATAR_FILES = ("avatar.json", "maps.npy", "gaussians.npz", "frames.npz", "head.npz")
BARY_TOLERANCE = 1e-3
"""How far a stored barycentric may lie outside its triangle (float32 round-off)."""


def add_to_description(path: str | os.PathLike, entries: dict) -> None:
    """Adds ``entries`` to the ``avatar.json`` of the avatar directory ``path`` (rewritten
    atomically)."""
    meta_path = Path(path) / "avatar.json"
    with reading(meta_path, "avatar description (JSON)"):
        meta = json.loads(meta_path.read_text())
    meta.update(entries)
    write_bytes_atomically(meta_path, json.dumps(meta, indent=2).encode())


def load_avatar(path: str | os.PathLike) -> Avatar:
    """Reads an avatar directory, every file from the same version of it even while another
    process saves a new one. Raises ``FileNotFoundError`` for a missing file,
    :class:`~urhead.errors.CorruptFileError` for a damaged one, and
    :class:`~urhead.errors.InvalidArgumentError` / :class:`~urhead.errors.ShapeError` naming
    the file and what does not fit (shapes, non-finite values, UVs outside [0, 1],
    barycentrics outside their triangle, a head other than the recorded one)."""
    return load_avatar_and_description(path)[0]


def load_avatar_and_description(path: str | os.PathLike) -> tuple[Avatar, dict]:
    """:func:`load_avatar` and the ``avatar.json`` it was read with (the fit's config,
    metrics, subject and camera), both from the same version of the folder."""
    path = Path(path)
    with _open_together(path) as files:
        return _read_avatar(path, files)


@contextmanager
def _open_together(path: Path) -> Iterator[dict[str, BinaryIO]]:
    """Every file of the avatar opened through one handle on its folder: a folder renamed
    into place meanwhile does not mix versions (an opened file stays readable after its
    folder is replaced); a file gone because that happened mid-way means trying again."""
    if not (path / "avatar.json").is_file():
        raise FileNotFoundError(f"{path}: not an avatar directory (no avatar.json)")
    for attempt in range(3):
        folder = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
        files: dict[str, BinaryIO] = {}
        try:
            try:
                for name in AVATAR_FILES:
                    files[name] = os.fdopen(os.open(name, os.O_RDONLY, dir_fd=folder), "rb")
            except FileNotFoundError:
                if attempt < 2 and os.stat(folder).st_ino != os.stat(path).st_ino:
                    continue  # replaced while opening
                raise FileNotFoundError(
                    f"{path / name}: missing from the avatar directory"
                ) from None
            yield files
            return
        finally:
            for f in files.values():
                f.close()
            os.close(folder)


def _read_avatar(path: Path, files: dict[str, BinaryIO]) -> tuple[Avatar, dict]:
    meta_path = path / "avatar.json"
    with reading(meta_path, "avatar description (JSON)"):
        meta = json.loads(files["avatar.json"].read())
        if meta.get("format") != "urhead-avatar" or meta.get("format_version") != AVATAR_FORMAT:
            raise InvalidArgumentError(
                f"unsupported avatar format {meta.get('format')!r} "
                f"version {meta.get('format_version')!r} (expected {AVATAR_FORMAT})"
            )
        layout = MapLayout(
            int(meta["sh_degree"]),
            bool(meta["gaussians"]),
            offsets=bool(meta.get("offsets", False)),
            shading=bool(meta.get("shading", False)),
        )
        r = int(meta["resolution"])
        rows = int(meta.get("map_rows", r))
        e = int(meta["num_expr"])
        background = np.asarray(meta["background"], np.float32)
        depth_eps = float(meta["depth_eps"])
        if background.shape != (3,) or not np.all((background >= 0) & (background <= 1)):
            raise InvalidArgumentError(f"background must be 3 values in [0, 1], got {background}")
        if not math.isfinite(depth_eps) or depth_eps < 0:
            raise InvalidArgumentError(f"depth_eps must be finite and >= 0, got {depth_eps}")
    head = load_head(path / "head.npz", files["head.npz"])
    recorded = meta.get("head_sha256")
    if recorded is not None and recorded != head_fingerprint(head):
        raise InvalidArgumentError(
            f"{path / 'head.npz'}: is not the head the avatar was fitted with "
            "(its hash differs from the one in avatar.json)"
        )
    with reading(path / "maps.npy", "map array (.npy)"):
        maps = torch.from_numpy(np.load(files["maps.npy"], allow_pickle=False))
        _expect("maps.npy", maps, (rows, r, layout.channels))
        _finite("maps", maps)
    with reading(path / "gaussians.npz", "Gaussian table (.npz)"):
        with np.load(files["gaussians.npz"], allow_pickle=False) as g:
            uv, face, bary = (torch.from_numpy(g[k]) for k in ("uv", "face", "bary"))
        n = uv.shape[0]
        _expect("uv", uv, (n, 2))
        _expect("face", face, (n,))
        _expect("bary", bary, (n, 3))
        _finite("uv", uv)
        _finite("bary", bary)
        if n and (int(face.min()) < 0 or int(face.max()) >= head.num_faces):
            raise InvalidArgumentError(f"face ids outside [0, {head.num_faces})")
        if n and not bool(((uv >= 0) & (uv <= 1)).all()):
            raise InvalidArgumentError("uv outside [0, 1]")
        outside = (bary < -BARY_TOLERANCE).any(-1) | ((bary.sum(-1) - 1).abs() > BARY_TOLERANCE)
        if bool(outside.any()):
            raise InvalidArgumentError(
                f"bary of {int(outside.sum())} Gaussians lie outside their triangle"
            )
    with reading(path / "frames.npz", "frame table (.npz)"):
        with np.load(files["frames.npz"], allow_pickle=False) as f:
            timesteps = torch.from_numpy(f["timesteps"]).long()
            params = torch.from_numpy(f["params"])
            shape = torch.from_numpy(f["shape"])
            static = torch.from_numpy(f["static_offset"]) if "static_offset" in f.files else None
        _expect("params", params, (timesteps.shape[0], e + POSE_SIZE + 3))
        if shape.ndim != 1 or shape.shape[0] > head.num_shape:
            raise ShapeError(f"shape must be (S ≤ {head.num_shape},), got {tuple(shape.shape)}")
        if static is not None:
            _expect("static_offset", static, (head.num_vertices, 3))
        for name, t in (("params", params), ("shape", shape), ("static_offset", static)):
            if t is not None:
                _finite(name, t)
        if e > head.num_expr:
            raise ShapeError(f"num_expr {e} exceeds the head's {head.num_expr}")
    avatar = Avatar(
        head=head,
        layout=layout,
        maps=hugepages.copy(maps.float()),
        gaussian_uv=uv.float().contiguous(),
        gaussian_face=face.long(),
        gaussian_bary=bary.float().contiguous(),
        shape=shape.float(),
        static_offset=None if static is None else static.float(),
        timesteps=timesteps,
        frame_params=params.float().contiguous(),
        background=torch.from_numpy(background),
        depth_eps=depth_eps,
    )
    return avatar, meta


def _finite(name: str, t: torch.Tensor) -> None:
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        raise NonFiniteError(f"{name} holds NaN or infinite values")


def _expect(name: str, t: torch.Tensor, shape: tuple) -> None:
    if tuple(t.shape) != shape:
        raise ShapeError(f"{name} must be {shape}, got {tuple(t.shape)}")
