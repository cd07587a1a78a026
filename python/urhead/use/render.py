"""``urhead render AVATAR --out DIR``: a subject's frames side by side — ground truth |
avatar | mesh branch | error map, each panel labelled — as PNGs and an MP4, or
(``--orbit TIMESTEP``) an orbit of the camera around the head at one frame, avatar | mesh
branch.

The error map is the per-pixel mean absolute RGB error, coloured with OpenCV's JET map
from 0 (blue) to ``--error-scale`` and above (red), over the whole image. An orbit turns
the camera about the vertical through the head; by default within the yaw range the
capture saw (:mod:`urhead.use.orbit`), with ``--orbit-degrees`` through that many degrees.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from urhead._atomic import write_directory_atomically
from urhead._in_flight import in_flight
from urhead._progress import tracked
from urhead.data.images import write_bgr_png
from urhead.eval.metrics import frame_params
from urhead.use.common import (
    add_background_option,
    bgr_uint8,
    check_output_dir,
    frame_at,
    open_avatar,
    open_subject,
    split_frames,
    use_background,
)
from urhead.use.orbit import default_orbit_angles, orbit_cameras, sweep_angles
from urhead.use.panels import labelled_row
from urhead.use.video import write_mp4


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a subject's frames side by side with the avatar, or an orbit",
        description="Render the avatar on a subject's frames: DIR/frames/TTTTT.png and "
        "DIR/render.mp4 (H.264) with labelled panels ground truth | avatar | mesh branch | "
        "error map. With --orbit TIMESTEP instead: DIR/orbit_TTTTT/III.png and "
        "DIR/orbit_TTTTT.mp4, an orbit of the camera around the head (avatar | mesh "
        "branch); TIMESTEP may be any frame of the avatar or of its subject (held-out "
        "frames use their tracked FLAME parameters).",
    )
    p.add_argument("avatar", type=Path, help="avatar directory (the fit's OUT/avatar)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--subject", type=Path, default=None, help="subject folder (default: the fit's)")
    p.add_argument(
        "--split", choices=("test", "val", "train"), default="test", help="frames to render"
    )
    p.add_argument("--orbit", type=int, default=None, metavar="TIMESTEP", help="orbit this frame")
    p.add_argument("--orbit-steps", type=int, default=60, help="views in the orbit")
    p.add_argument(
        "--orbit-degrees",
        type=float,
        default=None,
        help="turn the camera through this many degrees (360: a full circle); default: "
        "from the frame's view to either end of the head yaw range of the avatar's frames "
        "and back, so no view shows the head turned further than the capture did",
    )
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
    if args.orbit is None:
        return _render_frames(opened, args)
    return _render_orbit(opened, args)


def _render_frames(opened, args: argparse.Namespace) -> int:
    avatar, occlusion = opened.avatar, opened.occlusion_aware
    subject = open_subject(opened, args.subject)
    use_background(opened, subject, args.background)
    frames = split_frames(subject, args.split)
    args.out.mkdir(parents=True, exist_ok=True)

    def fill(folder: Path):
        def row(frame) -> np.ndarray:
            row = side_by_side(avatar, frame, occlusion, args.error_scale)
            write_bgr_png(folder / f"{frame.timestep:05d}.png", row)
            return row

        rows = tracked(in_flight(row, frames), len(frames), "render")
        write_mp4(args.out / "render.mp4", rows, args.fps)

    with torch.no_grad():
        write_directory_atomically(args.out / "frames", fill)
    print(f"wrote {len(frames)} frames to {args.out / 'frames'} and {args.out / 'render.mp4'}")
    return 0


def _render_orbit(opened, args: argparse.Namespace) -> int:
    avatar, occlusion = opened.avatar, opened.occlusion_aware
    subject = open_subject(opened, args.subject, required=False)
    use_background(opened, None, args.background)  # no ground truth to match in an orbit
    try:
        params, camera = frame_at(opened, subject, args.orbit)
    except ValueError as e:
        raise ValueError(f"--orbit {args.orbit}: {e}") from None
    with torch.no_grad():
        if args.orbit_degrees is None:
            angles = default_orbit_angles(avatar, params, camera, args.orbit_steps)
        else:
            angles = sweep_angles(args.orbit_degrees, args.orbit_steps)
        cameras = orbit_cameras(avatar, params, camera, angles)
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"orbit_{args.orbit:05d}"

    def fill_orbit(folder: Path):
        def view(indexed) -> np.ndarray:
            i, (cam, angle) = indexed
            out = avatar.render(params, cam, occlusion_aware=occlusion)
            turn = f"{np.degrees(angle):+.0f} deg"
            row = labelled_row(
                [bgr_uint8(out.image), bgr_uint8(out.mesh.image)],
                [f"avatar {turn}", "mesh branch"],
            )
            write_bgr_png(folder / f"{i:03d}.png", row)
            return row

        views = enumerate(zip(cameras, angles, strict=True))
        rows = tracked(in_flight(view, views), len(cameras), "orbit", unit="view")
        write_mp4(args.out / f"{name}.mp4", rows, args.fps)

    with torch.no_grad():
        write_directory_atomically(args.out / name, fill_orbit)
    span = np.degrees([min(angles), max(angles)])
    print(
        f"wrote {len(cameras)} views ({span[0]:+.0f}° to {span[1]:+.0f}°) to "
        f"{args.out / name} and {args.out / (name + '.mp4')}"
    )
    return 0


def side_by_side(avatar, frame, occlusion_aware: bool, error_scale: float) -> np.ndarray:
    """(bar + H, 4W, 3) uint8 BGR under labels: ground truth | avatar | mesh branch |
    error map."""
    import cv2

    out = avatar.render(frame_params(avatar, frame), frame.camera, occlusion_aware=occlusion_aware)
    image = out.image.clamp(0, 1)
    error = (image - frame.image).abs().mean(-1) / error_scale
    heat = cv2.applyColorMap(
        bgr_uint8(error[..., None].expand(-1, -1, 3))[..., 0], cv2.COLORMAP_JET
    )
    return labelled_row(
        [bgr_uint8(frame.image), bgr_uint8(image), bgr_uint8(out.mesh.image), heat],
        [
            f"ground truth t={frame.timestep}",
            "avatar",
            "mesh branch",
            f"|error| 0-{error_scale:g}",
        ],
    )
