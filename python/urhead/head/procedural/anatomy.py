"""Landmarks and the signed distance field of the built-in head, in metres.

FLAME's frame: y up, z out of the face, +x the subject's left. The eyes' midpoint is at
height ``EYE_Y``; an average adult: 0.23 m chin to crown, eyes 63 mm apart.
"""

from __future__ import annotations

import numpy as np

EYE_Y = 0.03
EYE_X = 0.0315  # half the interocular distance
EYE_Z = 0.062
EYE_RADIUS = 0.0120
MOUTH_Y = EYE_Y - 0.074
MOUTH_HALF_WIDTH = 0.0245
CHIN_Y = EYE_Y - 0.122
CROWN_Y = EYE_Y + 0.108
NECK_AXIS_Z = -0.022
NECK_BOTTOM_Y = EYE_Y - 0.215

RAY_CENTRE = np.array([0.0, EYE_Y - 0.018, -0.006])
"""Rays for the head surface leave from here (the head is star-shaped about it)."""

JOINTS = np.array(
    [
        [0.0, EYE_Y - 0.180, NECK_AXIS_Z],  # root: base of the neck
        [0.0, EYE_Y - 0.078, NECK_AXIS_Z - 0.004],  # neck: top of the spine
        [0.0, EYE_Y - 0.030, -0.004],  # jaw: the hinge between the two TMJs
        [EYE_X, EYE_Y, EYE_Z],  # left eye
        [-EYE_X, EYE_Y, EYE_Z],  # right eye
    ]
)


def _ellipsoid(p, centre, radii):
    """Approximate signed distance to an ellipsoid (exact on the surface, a bound off it)."""
    q = (p - centre) / radii
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / radii, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _capsule(p, a, b, ra, rb):
    """Distance to a tapered capsule from ``a`` (radius ra) to ``b`` (radius rb)."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    closest = a + t[..., None] * ab
    return np.linalg.norm(p - closest, axis=-1) - (ra + (rb - ra) * t)


def _smooth_union(a, b, k):
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smooth_subtract(a, b, k):
    """``a`` minus ``b``."""
    h = np.clip(0.5 - 0.5 * (a + b) / k, 0.0, 1.0)
    return a + (-b - a) * h + k * h * (1.0 - h)


def _lip(q, y, radius, z_back):
    """A lip: a chain of capsules along the dental arch at height ``y``, ``radius`` thick
    in the middle and thin at the corners; ``z_back`` sinks it into the muzzle."""
    x = np.linspace(0.0, MOUTH_HALF_WIDTH + 0.003, 6)
    z = 0.0905 - z_back - 14.0 * x**2
    r = radius * (1 - (x / x[-1]) ** 2) ** 0.5 + 0.0012
    pts = np.stack([x, np.full_like(x, y), z], 1)
    return np.min([_capsule(q, pts[k], pts[k + 1], r[k], r[k + 1]) for k in range(len(x) - 1)], 0)


def head_sdf(p: np.ndarray) -> np.ndarray:
    """(..., 3) points → (...,) signed distance (negative inside) to the skin, without the
    ears (separate meshes) and with closed lips and eyelids over the eyeballs."""
    x = np.abs(p[..., 0:1])
    q = np.concatenate([x, p[..., 1:]], -1)  # mirror: model the left half
    e = EYE_Y
    d = _ellipsoid(q, np.array([0.0, e + 0.012, -0.018]), np.array([0.075, 0.098, 0.099]))
    face = _ellipsoid(q, np.array([0.0, e - 0.045, 0.018]), np.array([0.060, 0.072, 0.066]))
    d = _smooth_union(d, face, 0.03)
    jaw = _ellipsoid(q, np.array([0.0, e - 0.088, 0.012]), np.array([0.056, 0.036, 0.068]))
    d = _smooth_union(d, jaw, 0.02)
    chin = _ellipsoid(q, np.array([0.0, e - 0.110, 0.064]), np.array([0.020, 0.016, 0.018]))
    d = _smooth_union(d, chin, 0.012)
    cheek = _ellipsoid(q, np.array([0.043, e - 0.024, 0.050]), np.array([0.024, 0.018, 0.022]))
    d = _smooth_union(d, cheek, 0.025)
    brow = _capsule(
        q, np.array([0.0, e + 0.016, 0.079]), np.array([0.046, e + 0.017, 0.064]), 0.009, 0.007
    )
    d = _smooth_union(d, brow, 0.012)
    # eye socket, then the lids wrapped over the eyeball
    socket = _ellipsoid(
        q, np.array([EYE_X, e + 0.001, EYE_Z + 0.020]), np.array([0.019, 0.014, 0.014])
    )
    d = _smooth_subtract(d, socket, 0.008)
    lids = _ellipsoid(q, np.array([EYE_X, e, EYE_Z]), np.full(3, EYE_RADIUS + 0.0016))
    d = _smooth_union(d, lids, 0.004)
    # nose: bridge, tip, wings
    bridge = _capsule(
        q, np.array([0.0, e + 0.004, 0.080]), np.array([0.0, e - 0.036, 0.106]), 0.0055, 0.0085
    )
    d = _smooth_union(d, bridge, 0.008)
    tip = _ellipsoid(q, np.array([0.0, e - 0.043, 0.104]), np.array([0.0105, 0.0095, 0.0105]))
    d = _smooth_union(d, tip, 0.006)
    wing = _ellipsoid(q, np.array([0.0120, e - 0.049, 0.089]), np.array([0.0075, 0.0068, 0.0085]))
    d = _smooth_union(d, wing, 0.008)
    # muzzle over the teeth, then the lips as arcs that thin towards the corners
    muzzle = _ellipsoid(q, np.array([0.0, MOUTH_Y - 0.002, 0.046]), np.array([0.040, 0.034, 0.043]))
    d = _smooth_union(d, muzzle, 0.02)
    d = _smooth_union(d, _lip(q, MOUTH_Y + 0.0042, 0.0054, 0.0022), 0.004)
    d = _smooth_union(d, _lip(q, MOUTH_Y - 0.0054, 0.0062, 0.0032), 0.004)
    philtrum = _capsule(
        q, np.array([0.0, e - 0.058, 0.094]), np.array([0.0, MOUTH_Y + 0.010, 0.095]), 0.0045, 0.005
    )
    d = _smooth_union(d, philtrum, 0.006)
    # ear base and neck
    ear_base = _ellipsoid(q, np.array([0.068, e - 0.008, -0.022]), np.array([0.012, 0.022, 0.014]))
    d = _smooth_union(d, ear_base, 0.01)
    neck_r = np.array([0.052, 0.058])
    radial = np.linalg.norm(
        np.stack([q[..., 0] / neck_r[0], (q[..., 2] - NECK_AXIS_Z) / neck_r[1]], -1), axis=-1
    )
    neck = (radial - 1.0) * neck_r.min()
    neck = np.maximum(neck, q[..., 1] - (e - 0.04))  # the neck stops inside the head
    d = _smooth_union(d, neck, 0.025)
    return d
