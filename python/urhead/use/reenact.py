"""``urhead reenact AVATAR --driver SUBJECT_OR_NPZ --out FILE.mp4``: cross-identity
reenactment. The driver's expression, jaw / eye / neck pose and global rotation animate the
avatar; its identity (shape, offsets) is not used, and its translation is re-centred on
the avatar's: ``t = t_driver − mean(t_driver) + mean(t_avatar)``, so a driver filmed at
another distance stays in the avatar's framing. The view is the avatar's fitting camera.

A driver is a subject folder (all its timesteps, in time order) or an ``.npz`` of stacked
FLAME parameters, keys as FORMATS.md with a leading frame axis: ``expr`` (T, E),
``rotation``, ``neck_pose``, ``jaw_pose``, ``translation`` (T, 3), ``eyes_pose`` (T, 6)
(a singleton axis after T, as in per-timestep files, is accepted).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from urhead._in_flight import in_flight
from urhead._progress import tracked
from urhead.errors import InvalidArgumentError, ShapeError, reading
from urhead.model.avatar import POSE_SIZE, FlameParams
from urhead.use.common import (
    avatar_camera,
    bgr_uint8,
    check_output_file,
    open_avatar,
    open_subject,
)
from urhead.use.video import write_mp4

DRIVER_KEYS = {
    "expr": None,
    "rotation": 3,
    "neck_pose": 3,
    "jaw_pose": 3,
    "eyes_pose": 6,
    "translation": 3,
}


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "reenact",
        help="drive an avatar with another sequence's expression and pose (MP4 out)",
        description="Cross-identity reenactment: the driver's expression, jaw/eye/neck pose "
        "and global rotation animate the avatar (its identity is not used; its translation "
        "is re-centred on the avatar's). The driver is a subject folder or an .npz of "
        "stacked FLAME parameters (expr, rotation, neck_pose, jaw_pose, eyes_pose, "
        "translation, each with a leading frame axis).",
    )
    p.add_argument("avatar", type=Path, help="avatar directory (the fit's OUT/avatar)")
    p.add_argument("--driver", type=Path, required=True, help="subject folder or .npz")
    p.add_argument("--out", type=Path, required=True, help="output video (.mp4, H.264)")
    p.add_argument(
        "--subject",
        type=Path,
        default=None,
        help="the avatar's subject, only for avatars that record no camera (older fits)",
    )
    p.add_argument("--fps", type=float, default=25.0, help="MP4 frame rate")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    out = check_output_file(args.out, "--out", ".mp4")
    if not args.fps > 0:
        raise ValueError(f"--fps must be positive, got {args.fps}")
    opened = open_avatar(args.avatar)
    avatar = opened.avatar
    driver = load_driver(args.driver)
    subject = open_subject(opened, args.subject, required=False)
    camera = avatar_camera(opened, subject)
    params = driven_params(avatar, driver)

    def image(p) -> np.ndarray:
        return bgr_uint8(avatar.render(p, camera, occlusion_aware=opened.occlusion_aware).image)

    with torch.no_grad():
        images = tracked(in_flight(image, params), len(params), "reenact")
        count = write_mp4(out, images, args.fps)
    print(f"wrote {count} frames to {out}")
    return 0


def load_driver(path: Path) -> dict[str, np.ndarray]:
    """The driver's stacked FLAME parameters ``{key: (T, width)}``."""
    path = Path(path)
    if path.is_dir():
        from urhead.data import load_subject

        subject = load_subject(path)
        records = {}
        for split in (subject.train, subject.val, subject.test):
            for r in split.records:
                records.setdefault(r.timestep, r)
        flames = [subject.flame[records[t].flame_path] for t in sorted(records)]
        if not flames:
            raise InvalidArgumentError(f"--driver {path}: the subject has no frames")
        stacked = {k: np.stack([np.asarray(f[k]).reshape(-1) for f in flames]) for k in DRIVER_KEYS}
    elif path.is_file():
        if path.suffix != ".npz":
            raise InvalidArgumentError(f"--driver {path}: must be a subject folder or an .npz")
        with reading(path, "FLAME parameter file (.npz)"), np.load(path, allow_pickle=False) as z:
            missing = [k for k in DRIVER_KEYS if k not in z.files]
            if missing:
                raise InvalidArgumentError(f"--driver {path}: missing keys {missing}")
            stacked = {k: np.asarray(z[k], np.float32) for k in DRIVER_KEYS}
        t = stacked["expr"].shape[0] if stacked["expr"].ndim else 0
        for k, width in DRIVER_KEYS.items():
            a = stacked[k]
            if a.ndim < 1 or a.shape[0] != t:
                raise ShapeError(f"--driver {path}: {k} must have {t} frames, got {a.shape}")
            a = a.reshape(t, -1)
            if width is not None and a.shape[1] != width:
                raise ShapeError(f"--driver {path}: {k} must be ({t}, {width}), got {a.shape}")
            stacked[k] = a
        if t == 0:
            raise InvalidArgumentError(f"--driver {path}: no frames")
    else:
        raise FileNotFoundError(f"--driver {path}: no such subject folder or .npz file")
    for k, a in stacked.items():
        if not np.isfinite(a).all():
            raise InvalidArgumentError(f"--driver {path}: {k} has non-finite values")
    return {k: a.astype(np.float32) for k, a in stacked.items()}


def driven_params(avatar, driver: dict[str, np.ndarray]) -> list[FlameParams]:
    """One :class:`FlameParams` per driver frame (expression truncated or zero-padded to
    the avatar's count; translation re-centred on the avatar's mean)."""
    e = avatar.num_expr
    avatar_mean = avatar.frame_params[:, e + POSE_SIZE :].detach().double().mean(0)
    transl = torch.from_numpy(driver["translation"]).double()
    transl = (transl - transl.mean(0) + avatar_mean).float()
    params = []
    for i in range(driver["expr"].shape[0]):
        flame = {k: driver[k][i] for k in DRIVER_KEYS}
        p = avatar.params_from_flame(flame)
        params.append(p._replace(transl=transl[i]))
    return params
