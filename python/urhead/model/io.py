"""The avatar directory (FORMATS.md "Avatar directory"), self-contained so render, eval,
export and reenactment need no training data:

```
avatar.json     format version, map layout and resolution, counts, background, config
maps.npy        (R, R, channels) float32 UV maps, layout in avatar.json
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
import os
from pathlib import Path

import numpy as np
import torch

from urhead.errors import InvalidArgumentError, ShapeError
from urhead.files import write_directory_atomically
from urhead.head import load_head, save_head
from urhead.model.avatar import POSE_SIZE, Avatar
from urhead.model.layout import MapLayout

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
        "channels": layout.channels,
        "num_gaussians": avatar.num_gaussians,
        "num_expr": avatar.num_expr,
        "num_frames": int(avatar.timesteps.shape[0]),
        "background": avatar.background.tolist(),
        "depth_eps": avatar.depth_eps,
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


def load_avatar(path: str | os.PathLike) -> Avatar:
    """Reads an avatar directory. Raises ``FileNotFoundError`` for a missing file and
    :class:`~urhead.errors.InvalidArgumentError` / :class:`~urhead.errors.ShapeError`
    naming what does not fit."""
    path = Path(path)
    meta_path = path / "avatar.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{path}: not an avatar directory (no avatar.json)")
    meta = json.loads(meta_path.read_text())
    if meta.get("format") != "urhead-avatar" or meta.get("format_version") != AVATAR_FORMAT:
        raise InvalidArgumentError(
            f"{meta_path}: unsupported avatar format {meta.get('format')!r} "
            f"version {meta.get('format_version')!r} (expected {AVATAR_FORMAT})"
        )
    for name in ("maps.npy", "gaussians.npz", "frames.npz", "head.npz"):
        if not (path / name).is_file():
            raise FileNotFoundError(f"{path / name}: missing from the avatar directory")
    head = load_head(path / "head.npz")
    layout = MapLayout(
        int(meta["sh_degree"]),
        bool(meta["gaussians"]),
        offsets=bool(meta.get("offsets", False)),
        shading=bool(meta.get("shading", False)),
    )
    maps = torch.from_numpy(np.load(path / "maps.npy", allow_pickle=False))
    r = int(meta["resolution"])
    _expect("maps.npy", maps, (r, r, layout.channels))
    with np.load(path / "gaussians.npz", allow_pickle=False) as g:
        uv, face, bary = (torch.from_numpy(g[k]) for k in ("uv", "face", "bary"))
    n = uv.shape[0]
    _expect("gaussians.npz uv", uv, (n, 2))
    _expect("gaussians.npz face", face, (n,))
    _expect("gaussians.npz bary", bary, (n, 3))
    if n and (int(face.min()) < 0 or int(face.max()) >= head.num_faces):
        raise InvalidArgumentError(f"{path}/gaussians.npz: face ids outside [0, {head.num_faces})")
    with np.load(path / "frames.npz", allow_pickle=False) as f:
        timesteps = torch.from_numpy(f["timesteps"]).long()
        params = torch.from_numpy(f["params"])
        shape = torch.from_numpy(f["shape"])
        static = torch.from_numpy(f["static_offset"]) if "static_offset" in f.files else None
    e = int(meta["num_expr"])
    _expect("frames.npz params", params, (timesteps.shape[0], e + POSE_SIZE + 3))
    if shape.ndim != 1 or shape.shape[0] > head.num_shape:
        raise ShapeError(
            f"frames.npz shape must be (S ≤ {head.num_shape},), got {tuple(shape.shape)}"
        )
    if static is not None:
        _expect("frames.npz static_offset", static, (head.num_vertices, 3))
    if e > head.num_expr:
        raise ShapeError(f"num_expr {e} exceeds the head's {head.num_expr}")
    return Avatar(
        head=head,
        layout=layout,
        maps=maps.float().contiguous(),
        gaussian_uv=uv.float().contiguous(),
        gaussian_face=face.long(),
        gaussian_bary=bary.float().contiguous(),
        shape=shape.float(),
        static_offset=None if static is None else static.float(),
        timesteps=timesteps,
        frame_params=params.float().contiguous(),
        background=torch.tensor(meta["background"], dtype=torch.float32),
        depth_eps=float(meta["depth_eps"]),
    )


def _expect(name: str, t: torch.Tensor, shape: tuple) -> None:
    if tuple(t.shape) != shape:
        raise ShapeError(f"{name} must be {shape}, got {tuple(t.shape)}")
