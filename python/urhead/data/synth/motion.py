"""The performance of a synthetic subject: a talking, expressive sequence (jaw, lip shapes,
smile, brows, blinks, gaze saccades) with head rotation, and the tracking noise added to
the exported FLAME parameters."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FPS = 25.0


@dataclass(frozen=True)
class Performance:
    """Per-frame ground truth. ``expr`` (T, E) coefficients of the head's expression
    columns; ``pose`` (T, 15) FLAME pose (global, neck, jaw, left eye, right eye);
    ``transl`` (T, 3); ``activation`` named wrinkle drivers (T,) in [0, 1]."""

    expr: np.ndarray
    pose: np.ndarray
    transl: np.ndarray
    activation: dict


def _smooth_noise(rng, n, cutoff_frames, scale=1.0):
    """(n,) band-limited noise with unit-ish spread: white noise low-passed by a Gaussian
    kernel of ``cutoff_frames``."""
    pad = int(4 * cutoff_frames) + 1
    white = rng.normal(size=n + 2 * pad)
    x = np.arange(-pad, pad + 1)
    kernel = np.exp(-0.5 * (x / cutoff_frames) ** 2)
    out = np.convolve(white, kernel / np.sqrt((kernel**2).sum()), mode="valid")[:n]
    return out * scale


def _events(rng, n, mean_gap, length, shape_power=1.0):
    """(n,) sum of bumps of ``length`` frames at random times (a Poisson-like process
    with gaps around ``mean_gap`` frames), each 0 → 1 → 0."""
    out = np.zeros(n)
    t = rng.uniform(0, mean_gap)
    while t < n:
        centre = int(t)
        half = max(1, int(length / 2))
        x = np.arange(centre - half, centre + half + 1)
        ok = (x >= 0) & (x < n)
        bump = np.sin(np.pi * (x - (centre - half)) / (2 * half)) ** 2
        out[x[ok]] = np.maximum(out[x[ok]], bump[ok] ** shape_power)
        t += mean_gap * rng.uniform(0.5, 1.5)
    return out


def performance(
    rng: np.random.Generator,
    num_frames: int,
    expression_names: tuple,
    num_expr: int,
    *,
    max_yaw_deg: float,
    expression_scale: float,
) -> Performance:
    """A talking sequence: speech in phrases (jaw at syllable rate, lip shapes), slow
    smiles and brow raises, blinks every 2–5 s, gaze saccades, head turns sweeping the
    full ±``max_yaw_deg`` range with pitch and roll."""
    n = num_frames
    s = expression_scale

    # Speech: phrases of 1.5–4 s separated by pauses; syllables at ~4.5 Hz inside.
    speaking = np.zeros(n)
    k = int(rng.uniform(0, 0.5) * FPS)
    while k < n:
        length = int(rng.uniform(1.5, 4.0) * FPS)
        speaking[k : k + length] = 1
        k += length + int(rng.uniform(0.4, 1.5) * FPS)
    speaking = np.convolve(np.pad(speaking, 2, mode="edge"), np.ones(5) / 5, mode="valid")
    syllable_phase = 2 * np.pi * np.cumsum(4.5 + 1.2 * _smooth_noise(rng, n, 8)) / FPS
    syllables = 0.5 + 0.5 * np.sin(syllable_phase)
    jaw = speaking * (0.04 + 0.2 * syllables**1.5) * s + 0.02 * np.clip(
        _smooth_noise(rng, n, 10), 0, None
    )
    lip_a = speaking * np.clip(_smooth_noise(rng, n, 3), 0, None) * 0.6 * s
    lip_b = speaking * np.clip(_smooth_noise(rng, n, 3), 0, None) * 0.6 * s

    smile = np.clip(0.25 + 0.5 * _smooth_noise(rng, n, 40), 0, 1) * s
    brow = (
        np.clip(
            _events(rng, n, 5 * FPS, 1.2 * FPS) * rng.uniform(0.6, 1.0)
            + 0.15 * _smooth_noise(rng, n, 20),
            0,
            1,
        )
        * s
    )
    frown = np.clip(0.6 * _smooth_noise(rng, n, 50) - 0.3, 0, 1) * s
    blink = _events(rng, n, 3.5 * FPS, 5, shape_power=0.7)
    squint = np.clip(0.5 * smile + 0.2 * _smooth_noise(rng, n, 30), 0, 1)

    expr = np.zeros((n, num_expr))
    named = {
        "smile": smile,
        "brow_raise": brow,
        "blink": blink,
        "pucker": lip_a,
        "funnel": lip_b * 0.7,
        "mouth_stretch": 0.3 * lip_b,
        "frown": frown,
        "squint": 0.4 * squint,
        "lower_lip_down": 0.5 * speaking * syllables * s,
    }
    for name, curve in named.items():
        if name in expression_names:
            expr[:, expression_names.index(name)] = curve
    # The anonymous columns: small smooth variation.
    for j in range(len(expression_names), num_expr):
        expr[:, j] = 0.15 * s * _smooth_noise(rng, n, 30)

    # Head: yaw sweeps the whole range (a slow oscillation with a random phase), pitch and
    # roll smaller; a nod accent while speaking.
    yaw_period = rng.uniform(7, 10) * FPS
    phase = rng.uniform(0, 2 * np.pi)
    yaw = np.radians(max_yaw_deg) * np.sin(2 * np.pi * np.arange(n) / yaw_period + phase)
    yaw = yaw * np.clip(0.85 + 0.15 * _smooth_noise(rng, n, 50), 0, 1)
    pitch = np.radians(8) * _smooth_noise(rng, n, 40) * 0.7 + np.radians(3) * speaking * (
        syllables - 0.5
    )
    roll = np.radians(5) * _smooth_noise(rng, n, 60) * 0.7
    neck = np.stack([0.3 * pitch, 0.25 * yaw, 0.3 * roll], 1)
    glob = np.stack([0.7 * pitch, 0.75 * yaw, 0.7 * roll], 1)

    # Gaze: saccades between fixations every 0.4–1.5 s, counter-rotating partly with yaw.
    fix_yaw, fix_pitch = np.zeros(n), np.zeros(n)
    k = 0
    while k < n:
        length = int(rng.uniform(0.4, 1.5) * FPS)
        fix_yaw[k : k + length] = rng.uniform(-0.25, 0.25)
        fix_pitch[k : k + length] = rng.uniform(-0.12, 0.12)
        k += length
    quick = np.exp(-np.arange(4) / 1.2)
    quick /= quick.sum()
    gaze_yaw = np.convolve(fix_yaw, quick, mode="full")[:n] - 0.3 * yaw
    gaze_pitch = np.convolve(fix_pitch, quick, mode="full")[:n]
    eye = np.stack([gaze_pitch, gaze_yaw, np.zeros(n)], 1)
    jaw_pose = np.stack([jaw, 0.02 * _smooth_noise(rng, n, 15), np.zeros(n)], 1)
    pose = np.concatenate([glob, neck, jaw_pose, eye, eye], 1)
    transl = np.stack(
        [
            0.008 * _smooth_noise(rng, n, 60),
            0.005 * _smooth_noise(rng, n, 60),
            0.01 * _smooth_noise(rng, n, 60),
        ],
        1,
    )
    activation = {
        "brow_raise": np.clip(brow, 0, 1),
        "smile": np.clip(smile, 0, 1),
        "squint": np.clip(squint, 0, 1),
        "frown": np.clip(frown, 0, 1),
        "jaw": np.clip(jaw / 0.25, 0, 1),
    }
    return Performance(
        expr.astype(np.float32), pose.astype(np.float32), transl.astype(np.float32), activation
    )


def tracking_noise(rng, perf: Performance, shape: np.ndarray, strength: float):
    """The parameters a tracker would have exported: ground truth plus per-frame jitter and
    a slow drift (rotation ~0.6° and translation ~2 mm at strength 1, expressions and jaw
    off by ~10 %), and a slightly wrong identity. Returns (shape, expr, pose, transl)."""
    n = len(perf.expr)
    drift = lambda scale, cutoff: np.stack(  # noqa: E731
        [_smooth_noise(rng, n, cutoff, scale) for _ in range(3)], 1
    )
    rot_noise = drift(0.007, 15) + rng.normal(scale=0.004, size=(n, 3))
    pose = perf.pose.copy()
    pose[:, 0:3] += strength * rot_noise
    pose[:, 3:6] += strength * rng.normal(scale=0.004, size=(n, 3))
    pose[:, 6:9] += strength * rng.normal(scale=0.02, size=(n, 3)) * np.array([1, 0.3, 0.3])
    pose[:, 9:15] += strength * rng.normal(scale=0.03, size=(n, 6))
    transl = perf.transl + strength * (drift(0.0015, 20) + rng.normal(scale=0.001, size=(n, 3)))
    expr = perf.expr + strength * rng.normal(scale=0.1, size=perf.expr.shape)
    shape_noisy = shape + strength * rng.normal(scale=0.1, size=shape.shape)
    return (
        shape_noisy.astype(np.float32),
        expr.astype(np.float32),
        pose.astype(np.float32),
        transl.astype(np.float32),
    )


EXTREME_POSES = np.radians(
    [
        # global pitch, global yaw, jaw opening, eye pitch, eye yaw (degrees)
        [0, 90, 0, 0, 0],
        [0, -90, 0, 0, 0],
        [45, 0, 0, 0, 0],
        [-45, 0, 0, 0, 0],
        [0, 0, 30, 0, 0],
        [0, 0, 0, 25, 35],
        [0, 0, 0, -25, -35],
        [45, 90, 30, 25, -35],
        [-45, -90, 30, -25, 35],
    ]
)
"""The poses of the ``extreme`` motion, cycled through: the head turned fully sideways or
tilted 45° up and down, the jaw wide open (30°), the eyes at their limits, and all at
once."""

OFF_SCREEN_SHIFTS = (0.0, 0.17, 0.6, -0.17)
"""Sideways head translations (metres) of the ``off_screen`` motion, cycled through: at
0.75 m with a 26° field of view the image edge is 0.17 m from the axis, so the head is
in view, half out, wholly out (an empty mask) and half out on the other side."""


def extreme_motion(perf: Performance) -> Performance:
    """``perf`` with its head and eye poses replaced, frame by frame, by
    :data:`EXTREME_POSES` (the neck straight; expressions and translation kept)."""
    n = len(perf.pose)
    picked = EXTREME_POSES[np.arange(n) % len(EXTREME_POSES)]
    pose = np.zeros((n, 15))
    pose[:, 0], pose[:, 1] = picked[:, 0], picked[:, 1]
    pose[:, 6] = picked[:, 2]
    for eye in (9, 12):
        pose[:, eye], pose[:, eye + 1] = picked[:, 3], picked[:, 4]
    activation = dict(perf.activation, jaw=np.clip(pose[:, 6] / 0.25, 0, 1))
    return Performance(perf.expr, pose.astype(np.float32), perf.transl, activation)


def off_screen_motion(perf: Performance) -> Performance:
    """``perf`` moved sideways frame by frame by :data:`OFF_SCREEN_SHIFTS`."""
    n = len(perf.transl)
    transl = perf.transl.copy()
    transl[:, 0] += np.asarray(OFF_SCREEN_SHIFTS)[np.arange(n) % len(OFF_SCREEN_SHIFTS)]
    return Performance(perf.expr, perf.pose, transl.astype(np.float32), perf.activation)


MOTIONS = {"talking": None, "extreme": extreme_motion, "off_screen": off_screen_motion}
"""The ``motion`` settings of a synthetic subject: the talking performance as it is, or
remade by one of these (NUMERICS.md cases 29 and 30)."""
