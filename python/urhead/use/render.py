"""``urhead render AVATAR --out DIR``: a subject's frames side by side — ground truth |
avatar | mesh branch | error map — as PNGs and an MP4, or (``--orbit TIMESTEP``) a yaw
orbit of the camera around the head at one frame, avatar | mesh branch.

The error map is the per-pixel mean absolute RGB error, coloured with OpenCV's JET map
from 0 (blue) to ``--error-scale`` and above (red), over the whole image.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

from urhead.camera import Camera
from urhead.eval.metrics import frame_params
from urhead.model.io import write_directory_atomically
from urhead.use.common import (
    add_background_option,
    avatar_camera,
    check_output_dir,
    open_avatar,
    open_subject,
    split_frames,
    to_uint8,
    use_background,
)
from urhead.use.video import write_mp4


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a subject's frames side by side with the avatar, or an orbit",
        description="Render the avatar on a subject's frames: DIR/frames/TTTTT.png and "
        "DIR/render.mp4 with ground truth | avatar | mesh branch | error map. With --orbit "
        "TIMESTEP instead: DIR/orbit_TTTTT/III.png and DIR/orbit_TTTTT.mp4, a yaw orbit of "
        "the camera around the head (avatar | mesh branch).",
    )
    p.add_argument("avatar", type=Path, help="avatar directory (the fit's OUT/avatar)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--subject", type=Path, default=None, help="subject folder (default: the fit's)")
    p.add_argument("--split", choices=("test", "val", "train"), default="test")
    p.add_argument("--orbit", type=int, default=None, metavar="TIMESTEP", help="orbit this frame")
    p.add_argument("--orbit-steps", type=int, default=60, help="views in the orbit")
    p.add_argument("--orbit-degrees", type=float, default=360.0, help="yaw range of the orbit")
    p.add_argument("--fps", type=float, default=25.0, help="MP4 frame rate")
    p.add_argument(
        "--error-scale", type=float, default=0.25, help="mean abs. error shown as full red"
    )
    add_background_option(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    check_output_dir(args.out, "--out")
    for name in ("fps", "error_scale", "orbit_steps"):
        if not getattr(args, name) > 0:
            raise ValueError(
                f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}"
            )
    opened = open_avatar(args.avatar)
    avatar = opened.avatar
    occlusion = opened.occlusion_aware
    if args.orbit is None:
        subject = open_subject(opened, args.subject)
        use_background(opened, subject, args.background)
        frames = split_frames(subject, args.split)
        args.out.mkdir(parents=True, exist_ok=True)

        def fill(folder: Path):
            def images():
                for frame in frames:
                    row = side_by_side(avatar, frame, occlusion, args.error_scale)
                    _write_png(folder / f"{frame.timestep:05d}.png", row)
                    yield row

            write_mp4(args.out / "render.mp4", images(), args.fps)

        with torch.no_grad():
            write_directory_atomically(args.out / "frames", fill)
        print(f"wrote {len(frames)} frames to {args.out / 'frames'} and {args.out / 'render.mp4'}")
        return 0

    subject = open_subject(opened, args.subject, required=False)
    use_background(opened, None, args.background)  # no ground truth to match in an orbit
    params, camera = orbit_frame(opened, subject, args.orbit)
    cameras = orbit_cameras(avatar, params, camera, args.orbit_steps, args.orbit_degrees)
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"orbit_{args.orbit:05d}"

    def fill_orbit(folder: Path):
        def images():
            for i, cam in enumerate(cameras):
                out = avatar.render(params, cam, occlusion_aware=occlusion)
                row = np.concatenate([to_uint8(out.image), to_uint8(out.mesh.image)], 1)
                _write_png(folder / f"{i:03d}.png", row)
                yield row

        write_mp4(args.out / f"{name}.mp4", images(), args.fps)

    with torch.no_grad():
        write_directory_atomically(args.out / name, fill_orbit)
    print(f"wrote {len(cameras)} views to {args.out / name} and {args.out / (name + '.mp4')}")
    return 0


def side_by_side(avatar, frame, occlusion_aware: bool, error_scale: float) -> np.ndarray:
    """(H, 4W, 3) uint8 BGR: ground truth | avatar | mesh branch | error map."""
    import cv2

    out = avatar.render(frame_params(avatar, frame), frame.camera, occlusion_aware=occlusion_aware)
    image = out.image.clamp(0, 1)
    error = (image - frame.image).abs().mean(-1) / error_scale
    heat = cv2.applyColorMap(to_uint8(error[..., None].expand(-1, -1, 3))[..., 0], cv2.COLORMAP_JET)
    return np.concatenate(
        [to_uint8(frame.image), to_uint8(image), to_uint8(out.mesh.image), heat], 1
    )


def orbit_frame(opened, subject, timestep: int):
    """The parameters and camera of ``timestep``: the avatar's trained row if it is a
    training frame, else the subject frame's tracked parameters."""
    avatar = opened.avatar
    record = None
    if subject is not None:
        for split in (subject.train, subject.val, subject.test):
            record = next((r for r in split.records if r.timestep == timestep), record)
    if bool((avatar.timesteps == timestep).any()):
        params = avatar.frame(timestep)
    elif record is not None:
        params = avatar.params_from_flame(subject.flame[record.flame_path])
    else:
        raise ValueError(
            f"--orbit {timestep}: not a frame of the avatar"
            + ("" if subject is None else f" or of the subject {subject.root}")
        )
    camera = record.camera if record is not None else avatar_camera(opened, subject)
    return params, camera


def orbit_cameras(avatar, params, camera: Camera, steps: int, degrees: float) -> list[Camera]:
    """``steps`` cameras turned about the vertical axis (the camera's image-up direction)
    through the centre of the posed head, evenly over ``degrees`` (a full circle does not
    repeat its first view)."""
    verts = avatar.render(params, camera, gaussians=False).mesh.verts.double()
    centre = verts.mean(0)
    view = camera.viewmat.double()
    up = -view[1, :3]  # the camera's image-up axis in world space
    span = math.radians(degrees)
    full = abs(abs(degrees) - 360.0) < 1e-9
    angles = np.linspace(0.0, span, steps, endpoint=not full) if steps > 1 else [0.0]
    cameras = []
    for a in angles:
        rot = _axis_angle(up, float(a))
        # Move the camera rigidly about the centre: c2w' = T(c)·R·T(−c)·c2w.
        move = torch.eye(4, dtype=torch.float64)
        move[:3, :3] = rot
        move[:3, 3] = centre - rot @ centre
        viewmat = view @ torch.linalg.inv(move)
        cameras.append(
            Camera(camera.K, viewmat, camera.width, camera.height, camera.near, camera.far)
        )
    return cameras


def _axis_angle(axis: torch.Tensor, angle: float) -> torch.Tensor:
    k = axis / axis.norm()
    cross = torch.tensor(
        [[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64
    )
    return (
        torch.eye(3, dtype=torch.float64)
        + math.sin(angle) * cross
        + (1 - math.cos(angle)) * cross @ cross
    )


def _write_png(path: Path, bgr: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), bgr):
        raise OSError(f"{path}: cannot write the PNG")
