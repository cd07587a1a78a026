"""Skinning weights, joint regressor, blendshapes and pose correctives of the built-in
head, all smooth functions of the rest positions."""

from __future__ import annotations

import numpy as np

from urhead.head.procedural import anatomy as A

ROOT, NECK, JAW, LEFT_EYE, RIGHT_EYE = range(5)


def smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _bump(p, centre, radii):
    """Smooth Gaussian falloff around ``centre`` with per-axis ``radii``."""
    q = (p - np.asarray(centre)) / np.asarray(radii)
    return np.exp(-0.5 * (q * q).sum(-1))


def skin_weights(p: np.ndarray, below_slit: np.ndarray, slit_lip: np.ndarray) -> np.ndarray:
    """(V, 5) weights for skin points ``p``. The head rides the neck joint; the neck skin
    blends into the root towards its base; below the mouth line and in front of the jaw
    hinge the skin follows the jaw. ``below_slit`` marks lower-lip rows and ``slit_lip``
    (0…1) how much a vertex belongs to the lips around the slit, where the cut, not the
    smooth field, decides upper (head) versus lower (jaw)."""
    y, z = p[:, 1], p[:, 2]
    head = smoothstep(A.EYE_Y - 0.215, A.EYE_Y - 0.12, y)
    # boundary height of the jaw's skin: the mouth line at the front rising to the hinge
    f = np.clip((0.078 - z) / 0.08, 0, 1)
    boundary = A.MOUTH_Y + (A.JOINTS[JAW, 1] - 0.01 - A.MOUTH_Y) * f
    width = 0.004 + 0.02 * f
    field = smoothstep(-0.5 * width, 0.5 * width, boundary - y)
    field *= smoothstep(-0.04, -0.008, z)  # behind the hinge: head
    field *= smoothstep(A.CHIN_Y - 0.06, A.CHIN_Y - 0.015, y)  # under the chin: fades into the neck
    jaw = (1 - slit_lip) * field + slit_lip * below_slit
    w = np.zeros((len(p), 5))
    w[:, ROOT] = 1 - head
    w[:, JAW] = head * jaw
    w[:, NECK] = head * (1 - jaw)
    return w


def min_norm_regressor(points: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Weights w (sum 1) with w @ points == target and the least ‖w‖: a joint regressed
    from nearby vertices, so it follows identity changes of that neighbourhood."""
    a = np.vstack([points.T, np.ones(len(points))])  # (4, K)
    b = np.r_[target, 1.0]
    return a.T @ np.linalg.solve(a @ a.T, b)


def skin_regions(p: np.ndarray) -> np.ndarray:
    """Labels for skin points (indices into REGION_NAMES): scalp above a hairline that
    drops from the forehead to the nape, neck below the jaw line, lips around the mouth,
    face elsewhere."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    labels = np.zeros(len(p), np.int32)  # face
    hairline = A.EYE_Y + 0.062 - 0.115 * np.clip((0.072 - z) / 0.175, 0, 1)
    hairline += 0.02 * np.exp(-(((z + 0.005) / 0.02) ** 2)) * (np.abs(x) > 0.05)  # temples
    jawline = A.CHIN_Y - 0.004 + 0.05 * np.clip((0.07 - z) / 0.075, 0, 1)
    lips = ((x / 0.027) ** 2 + ((y - A.MOUTH_Y + 0.0005) / 0.0115) ** 2 < 1) & (z > 0.074)
    labels[lips] = 5
    labels[(y < jawline) & (z > -0.01)] = 2
    labels[(y < A.EYE_Y - 0.085) & (z <= -0.01)] = 2
    labels[y > hairline] = 1
    return labels


# --- expression and identity fields: (P, 3) rest points → (P, 3) displacement ---------


def _corner(side):
    return np.array([side * A.MOUTH_HALF_WIDTH, A.MOUTH_Y - 0.001, 0.077])


def smile(p, sides=(1.0, -1.0)):
    d = np.zeros_like(p)
    for s in sides:
        w = _bump(p, _corner(s), (0.014, 0.012, 0.03))
        d += w[:, None] * np.array([s * 0.006, 0.008, -0.004])
        cheek = _bump(p, [s * 0.04, A.EYE_Y - 0.03, 0.06], (0.018, 0.014, 0.03))
        d += cheek[:, None] * np.array([s * 0.001, 0.003, 0.002])
    return d


def brow_raise(p):
    w = _bump(p, [0.0, A.EYE_Y + 0.03, 0.07], (0.06, 0.022, 0.05))
    return w[:, None] * np.array([0, 0.008, 0.0])


def frown(p):
    d = np.zeros_like(p)
    for s in (1.0, -1.0):
        w = _bump(p, [s * 0.022, A.EYE_Y + 0.017, 0.075], (0.016, 0.01, 0.03))
        d += w[:, None] * np.array([-s * 0.003, -0.0035, 0.001])
    return d


def pucker(p):
    w = _bump(p, [0, A.MOUTH_Y, 0.085], (0.022, 0.014, 0.03))
    d = np.zeros_like(p)
    d[:, 0] = -0.5 * p[:, 0] * w
    d[:, 2] = 0.010 * w
    return d


def funnel(p):
    w = _bump(p, [0, A.MOUTH_Y, 0.085], (0.022, 0.014, 0.03))
    up = np.tanh((p[:, 1] - A.MOUTH_Y) / 0.002)
    return np.stack([-0.25 * p[:, 0] * w, 0.004 * up * w, 0.005 * w], 1)


def cheek_puff(p):
    d = np.zeros_like(p)
    for s in (1.0, -1.0):
        w = _bump(p, [s * 0.042, A.MOUTH_Y + 0.008, 0.05], (0.016, 0.018, 0.025))
        d += w[:, None] * np.array([s * 0.0065, 0, 0.002])
    return d


def mouth_stretch(p):
    d = np.zeros_like(p)
    for s in (1.0, -1.0):
        w = _bump(p, _corner(s), (0.013, 0.012, 0.03))
        d += w[:, None] * np.array([s * 0.005, -0.001, -0.002])
    return d


def sneer(p):
    d = np.zeros_like(p)
    for s in (1.0, -1.0):
        w = _bump(p, [s * 0.013, A.EYE_Y - 0.046, 0.09], (0.01, 0.012, 0.03))
        d += w[:, None] * np.array([0, 0.003, 0.0005])
    return d


def corners_down(p):
    d = np.zeros_like(p)
    for s in (1.0, -1.0):
        w = _bump(p, _corner(s), (0.012, 0.012, 0.03))
        d += w[:, None] * np.array([0, -0.0045, -0.001])
    return d


def lower_lip_down(p):
    below = smoothstep(0.0, 0.0015, A.MOUTH_Y - p[:, 1])
    w = _bump(p, [0, A.MOUTH_Y - 0.006, 0.085], (0.02, 0.01, 0.03)) * below
    return w[:, None] * np.array([0, -0.0045, 0.001])


def upper_lip_up(p):
    above = smoothstep(0.0, 0.0015, p[:, 1] - A.MOUTH_Y)
    w = _bump(p, [0, A.MOUTH_Y + 0.006, 0.088], (0.02, 0.01, 0.03)) * above
    return w[:, None] * np.array([0, 0.0035, 0.001])


def eyes_wide(p):
    d = np.zeros_like(p)
    for s in (1.0, -1.0):
        w = _bump(p, [s * A.EYE_X, A.EYE_Y + 0.008, A.EYE_Z + 0.012], (0.012, 0.005, 0.01))
        d += w[:, None] * np.array([0, 0.0022, 0])
    return d


def squint(p):
    d = np.zeros_like(p)
    for s in (1.0, -1.0):
        w = _bump(p, [s * A.EYE_X, A.EYE_Y - 0.006, A.EYE_Z + 0.012], (0.012, 0.005, 0.01))
        d += w[:, None] * np.array([0, 0.0018, 0.0005])
    return d


SEMANTIC_EXPRESSIONS = (
    "smile",
    "brow_raise",
    "blink",
    "pucker",
    "funnel",
    "cheek_puff",
    "mouth_stretch",
    "frown",
    "sneer",
    "mouth_corners_down",
    "lower_lip_down",
    "upper_lip_up",
    "smile_left",
    "smile_right",
    "blink_left",
    "blink_right",
    "eyes_wide",
    "squint",
)
"""Names of the leading expression columns (coefficient 1 = the full expression); the
remaining columns are smooth, small random deformations of the face."""

EXPRESSION_FIELDS = {
    "smile": smile,
    "brow_raise": brow_raise,
    "pucker": pucker,
    "funnel": funnel,
    "cheek_puff": cheek_puff,
    "mouth_stretch": mouth_stretch,
    "frown": frown,
    "sneer": sneer,
    "mouth_corners_down": corners_down,
    "lower_lip_down": lower_lip_down,
    "upper_lip_up": upper_lip_up,
    "smile_left": lambda p: smile(p, (1.0,)),
    "smile_right": lambda p: smile(p, (-1.0,)),
    "eyes_wide": eyes_wide,
    "squint": squint,
}


def _scale_about(p, centre, scale, weight):
    return (p - centre) * (np.asarray(scale) - 1) * weight[:, None]


SEMANTIC_IDENTITY = (
    "head_width",
    "face_length",
    "nose_size",
    "jaw_width",
    "head_depth",
    "chin_forward",
    "cheekbones",
    "nose_bridge",
    "lip_fullness",
    "brow_ridge",
    "forehead_slope",
    "neck_width",
)
"""Names of the leading identity columns (coefficient 1 ≈ a large but plausible change);
the remaining columns are smooth random deformations of the whole head."""


def identity_field(name: str, p: np.ndarray) -> np.ndarray:
    ones = np.ones(len(p))
    e = A.EYE_Y
    if name == "head_width":
        return _scale_about(p, [0, e, 0], [1.07, 1, 1], ones)
    if name == "face_length":
        w = smoothstep(e + 0.01, e - 0.03, p[:, 1]) * smoothstep(-0.04, 0.0, p[:, 2])
        return _scale_about(p, [0, e, 0], [1, 1.07, 1], w)
    if name == "nose_size":
        w = _bump(p, [0, e - 0.04, 0.1], (0.016, 0.025, 0.02))
        return _scale_about(p, [0, e - 0.045, 0.082], [1.2, 1.15, 1.25], w)
    if name == "jaw_width":
        w = smoothstep(A.MOUTH_Y + 0.01, A.MOUTH_Y - 0.02, p[:, 1]) * smoothstep(
            A.CHIN_Y - 0.07, A.CHIN_Y - 0.02, p[:, 1]
        )
        return _scale_about(p, [0, 0, 0], [1.12, 1, 1], w)
    if name == "head_depth":
        w = smoothstep(0.04, -0.04, p[:, 2])
        return _scale_about(p, [0, 0, 0.02], [1, 1, 1.08], w)
    if name == "chin_forward":
        return _bump(p, [0, A.CHIN_Y + 0.008, 0.07], (0.025, 0.018, 0.04))[:, None] * np.array(
            [0, -0.001, 0.006]
        )
    if name == "cheekbones":
        d = np.zeros_like(p)
        for s in (1.0, -1.0):
            d += _bump(p, [s * 0.048, e - 0.022, 0.045], (0.015, 0.012, 0.02))[:, None] * np.array(
                [s * 0.004, 0, 0.002]
            )
        return d
    if name == "nose_bridge":
        return _bump(p, [0, e - 0.01, 0.085], (0.007, 0.018, 0.02))[:, None] * np.array(
            [0, 0, 0.004]
        )
    if name == "lip_fullness":
        w = _bump(p, [0, A.MOUTH_Y, 0.09], (0.02, 0.008, 0.015))
        up = np.tanh((p[:, 1] - A.MOUTH_Y) / 0.003)
        return np.stack([0 * w, 0.0015 * up * w, 0.0025 * w], 1)
    if name == "brow_ridge":
        return _bump(p, [0, e + 0.018, 0.078], (0.04, 0.008, 0.015))[:, None] * np.array(
            [0, 0, 0.004]
        )
    if name == "forehead_slope":
        w = smoothstep(e + 0.02, e + 0.09, p[:, 1]) * smoothstep(0.0, 0.06, p[:, 2])
        return w[:, None] * np.array([0, 0, -0.008])
    if name == "neck_width":
        w = smoothstep(A.EYE_Y - 0.1, A.EYE_Y - 0.16, p[:, 1])
        return _scale_about(p, [0, 0, A.NECK_AXIS_Z], [1.1, 1, 1.08], w)
    raise KeyError(name)


def random_fields(
    p: np.ndarray, count: int, rng: np.random.Generator, amplitude, centre_box
) -> np.ndarray:
    """(P, 3, count) smooth random deformations: sums of a few Gaussian bumps with random
    centres in ``centre_box`` ((lo, hi) corners), directions and widths; amplitudes fall
    off with the column index like a PCA spectrum."""
    lo, hi = (np.asarray(c, float) for c in centre_box)
    out = np.zeros((len(p), 3, count))
    for k in range(count):
        for _ in range(3):
            c = lo + (hi - lo) * rng.random(3)
            width = rng.uniform(0.015, 0.04)
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            w = _bump(p, c, (width, width, width))
            out[:, :, k] += w[:, None] * direction
        scale = amplitude / (1 + 0.15 * k) / max(np.abs(out[:, :, k]).max(), 1e-12)
        out[:, :, k] *= scale
    return out
