"""Orbits: cameras turned about the vertical through the head, and the default sweep that
stays within the yaw range the capture saw (a monocular video shows one side of the head
turning by some tens of degrees; views beyond that show what the fit never saw)."""

from __future__ import annotations

import math

import numpy as np
import torch

from urhead.camera import Camera

MIN_SWEEP_DEGREES = 10.0
"""The default sweep when the capture barely turns: ±5° about the frame's view."""


def camera_up(camera: Camera) -> torch.Tensor:
    """The camera's image-up axis in world space (float64)."""
    return -camera.viewmat.double()[1, :3]


def head_yaws(poses: torch.Tensor, up: torch.Tensor) -> np.ndarray:
    """The head's yaw (radians) about ``up`` for (N, ≥6) FLAME poses (global rotation, then
    neck): the twist about ``up`` of the global rotation followed by the neck's."""
    from scipy.spatial.transform import Rotation

    pose = poses[:, :6].detach().double().numpy()
    head = Rotation.from_rotvec(pose[:, 0:3]) * Rotation.from_rotvec(pose[:, 3:6])
    return _twist(head.as_quat(), up.numpy())


def _twist(quats_xyzw: np.ndarray, axis: np.ndarray) -> np.ndarray:
    along = quats_xyzw[:, :3] @ (axis / np.linalg.norm(axis))
    return 2 * np.arctan2(along, quats_xyzw[:, 3])


def default_orbit_angles(avatar, params, camera: Camera, steps: int) -> np.ndarray:
    """Camera turns (radians) for ``steps`` views: from the frame's own view (0) to one
    end of the captured yaw range, to the other end, and back, so the head is never seen
    turned further than some training frame showed it. Turning the camera by a shows the
    head turned by −a, so the turns lie in [yaw − max, yaw − min]."""
    up = camera_up(camera)
    e = avatar.num_expr
    yaws = head_yaws(avatar.frame_params[:, e:], up)
    here = float(head_yaws(params.pose[None], up)[0])
    low, high = here - float(yaws.max()), here - float(yaws.min())
    if high - low < math.radians(MIN_SWEEP_DEGREES):
        half = math.radians(MIN_SWEEP_DEGREES) / 2
        low, high = -half, half
    low, high = min(low, 0.0), max(high, 0.0)
    # 0 → high → low → 0, evenly along the path, the last view not repeating the first.
    path = np.array([0.0, high, low, 0.0])
    lengths = np.abs(np.diff(path))
    at = np.concatenate([[0.0], np.cumsum(lengths)])
    s = np.linspace(0.0, at[-1], steps, endpoint=False) if steps > 1 else np.zeros(1)
    return np.interp(s, at, path)


def sweep_angles(degrees: float, steps: int) -> np.ndarray:
    """Camera turns (radians) for an explicit ``--orbit-degrees``: from the frame's view
    through ``degrees``; a full circle does not repeat its first view."""
    span = math.radians(degrees)
    full = abs(abs(degrees) - 360.0) < 1e-9
    return np.linspace(0.0, span, steps, endpoint=not full) if steps > 1 else np.zeros(1)


def orbit_cameras(avatar, params, camera: Camera, angles) -> list[Camera]:
    """One camera per angle, turned about the camera's vertical axis through the centre of
    the posed head."""
    verts = avatar.render(params, camera, gaussians=False).mesh.verts.double()
    centre = verts.mean(0)
    view = camera.viewmat.double()
    up = camera_up(camera)
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
