"""What the avatar commands share: opening an avatar and its subject, choosing frames,
the camera to render from, and writing output files atomically."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from urhead.camera import Camera
from urhead.data.images import to_uint8
from urhead.errors import InvalidArgumentError
from urhead.model import Avatar
from urhead.model.io import add_to_description, load_avatar_and_description


@dataclass
class OpenedAvatar:
    avatar: Avatar
    meta: dict
    """avatar.json: the fit's config, metrics and, for fits since the recording was added,
    ``subject`` (its folder) and ``camera`` (the training camera)."""
    path: Path

    @property
    def occlusion_aware(self) -> bool:
        return bool(self.meta.get("config", {}).get("occlusion_aware", True))


def open_avatar(path: Path) -> OpenedAvatar:
    """Loads an avatar directory with an error naming the argument."""
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"AVATAR {path}: no such directory (pass the fit's OUT/avatar)")
    return OpenedAvatar(*load_avatar_and_description(path), path)


def open_subject(opened: OpenedAvatar, subject: Path | None, *, required: bool = True):
    """The subject given with ``--subject``, else the one the fit recorded; None when
    neither exists and ``required`` is False."""
    from urhead.data import load_subject

    if subject is None:
        candidates = recorded_subject_paths(opened)
        subject = next((p for p in candidates if p.is_dir()), None)
        if subject is None:
            if not required:
                return None
            where = (
                "records no subject"
                if not candidates
                else "records " + " and ".join(map(str, candidates)) + ", gone"
            )
            raise InvalidArgumentError(f"--subject is required: the avatar {where}")
    if not Path(subject).is_dir():
        raise FileNotFoundError(f"--subject {subject}: no such directory")
    return load_subject(subject)


def recorded_subject_paths(opened: OpenedAvatar) -> list[Path]:
    """Where avatar.json says the subject is: ``subject_relative`` (relative to the avatar
    directory, so an avatar moved together with its subject still finds it), then
    ``subject`` (absolute; a relative one is taken relative to the avatar directory)."""
    paths = []
    for key in ("subject_relative", "subject"):
        value = opened.meta.get(key)
        if isinstance(value, str) and value:
            p = Path(value)
            paths.append(p if p.is_absolute() else opened.path / p)
    return paths


def subject_record(avatar_dir: Path, subject_root: Path) -> dict:
    """The avatar.json entries that locate a subject: absolute, and relative to the
    avatar directory."""
    absolute = Path(subject_root).resolve()
    relative = os.path.relpath(absolute, Path(avatar_dir).resolve())
    return {"subject": str(absolute), "subject_relative": relative}


def add_subject_record(avatar_dir: Path, subject_root: Path) -> None:
    """Adds :func:`subject_record` to an avatar's avatar.json (rewritten atomically)."""
    add_to_description(avatar_dir, subject_record(avatar_dir, subject_root))


def add_background_option(parser) -> None:
    parser.add_argument(
        "--background",
        default=None,
        help="colour to render on: white, black or R,G,B (0-255); default: the one the avatar "
        "was fitted on. Checked against the subject's pixels outside the masks",
    )


def use_background(opened: OpenedAvatar, subject, requested: str | None) -> None:
    """Sets the avatar's background to ``--background`` (else keeps the recorded one),
    checked against the subject's data when there is a subject: a colour the frames'
    background contradicts is an error naming the subject."""
    from urhead.data.background import parse_background, subject_background

    if requested is not None:
        colour, by = parse_background(requested), "--background"
    else:
        colour, by = opened.avatar.background.tolist(), "the avatar's recorded background"
    if subject is not None:
        opened.avatar.background = subject_background(subject, colour, requested_by=by)
    else:
        opened.avatar.background = torch.tensor(colour, dtype=torch.float32)


def split_frames(subject, split: str):
    frames = getattr(subject, split)
    if len(frames) == 0:
        raise InvalidArgumentError(
            f"--split {split}: the subject {subject.root} has no {split} frames"
        )
    return frames


def avatar_camera(opened: OpenedAvatar, subject) -> Camera:
    """The camera the avatar was fitted with (recorded in avatar.json), else the subject's."""
    if "camera" in opened.meta:
        return Camera.from_dict(opened.meta["camera"])
    if subject is not None:
        for split in (subject.train, subject.test, subject.val):
            if len(split):
                return split.records[0].camera
    raise InvalidArgumentError("--subject is required: the avatar records no camera to render from")


def subject_records(subject) -> dict:
    """Every frame record of the subject by timestep (train first, then val, then test)."""
    records = {}
    if subject is not None:
        for split in (subject.train, subject.val, subject.test):
            for r in split.records:
                records.setdefault(r.timestep, r)
    return records


def frame_at(opened: OpenedAvatar, subject, timestep: int):
    """``(params, camera)`` of ``timestep``: the avatar's trained row if it is a training
    frame, else the subject frame's tracked FLAME parameters (held-out timesteps); the
    camera is the subject frame's, else the avatar's."""
    avatar = opened.avatar
    record = subject_records(subject).get(timestep)
    if bool((avatar.timesteps == timestep).any()):
        params = avatar.frame(timestep)
    elif record is not None:
        params = avatar.params_from_flame(subject.flame[record.flame_path])
    else:
        raise InvalidArgumentError(
            f"timestep {timestep} is not a frame of the avatar"
            + ("" if subject is None else f" or of the subject {subject.root}")
        )
    camera = record.camera if record is not None else avatar_camera(opened, subject)
    return params, camera


def selectable_timesteps(opened: OpenedAvatar, subject) -> list[int]:
    """The timesteps :func:`frame_at` can pose: the avatar's and the subject's."""
    avatar_steps = {int(t) for t in opened.avatar.timesteps.tolist()}
    return sorted(avatar_steps | set(subject_records(subject)))


def parse_timesteps(spec: str | None, available, default=None) -> list[int]:
    """``--frames`` "0,3,10-20" (timesteps, ranges inclusive) → sorted unique timesteps, all
    of which must be among ``available``; None → ``default`` (else all of ``available``)."""
    known = sorted(int(t) for t in available)
    if spec is None and default is not None:
        return sorted(int(t) for t in default)
    if spec is None:
        return known
    wanted: set[int] = set()
    for part in spec.split(","):
        match = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if match is None or (match[2] is not None and int(match[2]) < int(match[1])):
            raise InvalidArgumentError(
                f"--frames {spec!r}: {part.strip()!r} is not a timestep or a range a-b"
            )
        first = int(match[1])
        wanted.update(range(first, int(match[2] or first) + 1))
    unknown = sorted(wanted - set(known))
    if unknown:
        raise InvalidArgumentError(
            f"--frames: timesteps {_short(unknown)} are not frames of this avatar or its "
            f"subject ({len(known)} timesteps, {known[0]}–{known[-1]})"
        )
    return sorted(wanted)


def _short(values: list[int]) -> str:
    return ", ".join(map(str, values[:8])) + (" …" if len(values) > 8 else "")


def check_output_dir(path: Path, option: str) -> Path:
    """An output folder must be a folder or not exist yet; its parent is created."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InvalidArgumentError(f"{option} {path}: exists and is not a directory")
    return path


def check_output_file(path: Path, option: str, suffix: str) -> Path:
    path = Path(path)
    if path.suffix.lower() != suffix:
        raise InvalidArgumentError(f"{option} {path}: must end in {suffix}")
    if path.is_dir():
        raise InvalidArgumentError(f"{option} {path}: is a directory")
    return path


def bgr_uint8(image: torch.Tensor) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] → uint8 BGR for OpenCV."""
    return np.ascontiguousarray(to_uint8(image.detach().numpy())[..., ::-1])
