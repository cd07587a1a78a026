"""The skin of the built-in head: a grid of rays cast onto the signed distance field.

Rows run from the crown down to the neck's open end, columns around the vertical axis
(column 0 at the back, the face in the middle). Head rows are rays from
:data:`~anatomy.RAY_CENTRE` at polar angle θ; neck rows are horizontal rays from the neck
axis. Rows and columns are denser over the face. Three rows are bent to follow features
exactly: the mouth line (cut open into the lip slit) and, over each eye, the upper and
lower lid margins; the skin between the margins is tucked just inside the eyeball, where
the blink expression pulls it out to close the lids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from urhead.head.procedural import anatomy as A

COLUMNS = 84
HEAD_ROWS = 64
NECK_ROWS = 8
THETA_FIRST, THETA_LAST = 0.06, np.deg2rad(150.0)


@dataclass(frozen=True)
class Skin:
    verts: np.ndarray  # (N, 3) grid vertices (rows × columns) then the crown pole
    rows: int
    theta: np.ndarray  # (HEAD_ROWS, COLUMNS)
    mouth_row: int
    slit_columns: np.ndarray  # interior columns of the lip slit (duplicated vertices)
    lid_rows: tuple[int, int]  # upper and lower lid margin rows
    eyelid: np.ndarray  # (N,) bool: skin tucked behind the eyeball (the lids' hidden part)
    eyelid_depth: np.ndarray  # (N,) how far inside the eyeball it sits (0 elsewhere)

    def index(self, row, col):
        return np.asarray(row) * COLUMNS + np.asarray(col) % COLUMNS

    @property
    def pole(self) -> int:
        return self.rows * COLUMNS


def column_angles() -> np.ndarray:
    """φ per column in [−π, π): column 0 at the back, denser towards the face (φ = 0)."""
    u = -1.0 + 2.0 * np.arange(COLUMNS) / COLUMNS
    a = 0.42
    return np.pi * u * (a + (1 - a) * u * u)


def _row_angles() -> np.ndarray:
    """θ per head row: denser over the face (θ ≈ 70°…135°)."""
    fine = np.linspace(0, np.pi, 4001)
    density = 1 + 1.7 * np.exp(-(((fine - np.deg2rad(103)) / np.deg2rad(24)) ** 2))
    cdf = np.concatenate([[0], np.cumsum((density[1:] + density[:-1]) / 2)])
    lo, hi = np.interp([THETA_FIRST, THETA_LAST], fine, cdf)
    return np.interp(np.linspace(lo, hi, HEAD_ROWS), cdf, fine)


def _directions(theta, phi):
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), np.sin(theta) * np.cos(phi)], -1)


def cast(origins, dirs, t_max=0.26, steps=40, sdf=A.head_sdf) -> np.ndarray:
    """Distance along each ray to the outermost surface crossing, marching in from
    ``t_max`` and refining by bisection."""
    ts = np.linspace(t_max, 0.0, steps)
    inside = sdf(origins[..., None, :] + ts[:, None] * dirs[..., None, :]) < 0
    first = np.argmax(inside, axis=-1)
    lo = ts[first]  # inside
    hi = ts[np.maximum(first - 1, 0)]  # outside
    for _ in range(16):
        mid = 0.5 * (lo + hi)
        m_in = sdf(origins + mid[..., None] * dirs) < 0
        lo, hi = np.where(m_in, mid, lo), np.where(m_in, hi, mid)
    return 0.5 * (lo + hi)


def _head_points(theta, phi):
    dirs = _directions(theta, phi)
    origins = np.broadcast_to(A.RAY_CENTRE, dirs.shape)
    return origins + cast(origins, dirs)[..., None] * dirs


def _solve_theta(theta0, phi, target_y, iterations=12, reach=0.15):
    """θ per column whose ray hits the skin at height ``target_y``: bisection, since the
    hit height falls with θ but jumps across creases (the lips)."""
    lo, hi = theta0 - reach, theta0 + reach  # hit above / below the target
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        above = _head_points(mid, phi)[..., 1] > target_y
        lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
    return 0.5 * (lo + hi)


def almond(x_local):
    """Upper and lower lid margin heights (relative to EYE_Y) across one eye; ``x_local``
    runs −1 (inner corner) … 1 (outer corner)."""
    t = np.clip(x_local, -1, 1)
    open_ = np.clip(1 - t * t, 0, 1)
    tilt = 0.0012 * t
    upper = 0.0010 + tilt + 0.0056 * open_**0.65 * (1 - 0.12 * t)
    lower = 0.0003 + tilt - 0.0041 * open_**0.75 * (1 + 0.1 * t)
    return upper, lower


EYE_HALF_WIDTH = 0.0148


def _eye_local_x(x):
    """Position across the nearer eye: −1 at its inner corner, +1 at its outer corner."""
    return (np.abs(x) - A.EYE_X) / EYE_HALF_WIDTH


def build_skin() -> Skin:
    phi = column_angles()
    theta = np.repeat(_row_angles()[:, None], COLUMNS, 1)
    # the rows closest to the features at the front of the face
    centre_hits = _head_points(theta[:, COLUMNS // 2], np.zeros(HEAD_ROWS))
    mouth_row = int(np.argmin(np.abs(centre_hits[:, 1] - A.MOUTH_Y)))
    eye_col = int(np.argmin(np.abs(_head_points(theta[0, :] * 0 + 1.45, phi)[:, 0] - A.EYE_X)))
    eye_hits = _head_points(theta[:, eye_col], np.full(HEAD_ROWS, phi[eye_col]))
    upper_row = int(np.argmin(np.abs(eye_hits[:, 1] - (A.EYE_Y + 0.0062))))
    lower_row = upper_row + 3

    feature_rows = [mouth_row, upper_row, lower_row]
    row_x = _head_points(theta[feature_rows], phi[None])[..., 0]
    front = np.cos(phi) > 0.3
    targets, fades = [], []
    # mouth line: level, corners a touch lower
    x = row_x[0]
    targets.append(A.MOUTH_Y - 0.0012 * (x / A.MOUTH_HALF_WIDTH) ** 2)
    fades.append(front * np.clip((A.MOUTH_HALF_WIDTH + 0.02 - np.abs(x)) / 0.012, 0, 1))
    # lid margins
    for k, pick in ((1, 0), (2, 1)):
        xl = _eye_local_x(row_x[k])
        targets.append(A.EYE_Y + almond(xl)[pick])
        fades.append(front * np.clip((1.6 - np.abs(xl)) / 0.6, 0, 1))
    solved = _solve_theta(theta[feature_rows], phi[None], np.stack(targets))
    anchors = {row: (solved[k], fades[k]) for k, row in enumerate(feature_rows)}
    theta = _bend_rows(theta, anchors)
    # rows between the lid margins follow them evenly
    for k in range(upper_row + 1, lower_row):
        f = (k - upper_row) / (lower_row - upper_row)
        theta[k] = (1 - f) * theta[upper_row] + f * theta[lower_row]

    head = _mirrored_points(theta, phi)
    neck = _neck_rows(head[-1], phi)
    grid = np.concatenate([head, neck]).reshape(-1, 3)
    pole = _head_points(np.array([0.0]), np.array([0.0]))
    verts = np.concatenate([grid, pole])

    # tuck the skin between the lid margins inside the eyeball
    rows = HEAD_ROWS + NECK_ROWS
    eyelid = np.zeros(len(verts), bool)
    depth = np.zeros(len(verts))
    for k in range(upper_row + 1, lower_row):
        idx = k * COLUMNS + np.arange(COLUMNS)
        xl = _eye_local_x(verts[idx, 0])
        inside = front & (np.abs(xl) < 0.97)
        centre = np.stack(
            [
                np.sign(verts[idx, 0]) * A.EYE_X,
                np.full(COLUMNS, A.EYE_Y),
                np.full(COLUMNS, A.EYE_Z),
            ],
            1,
        )
        # deeper towards the lower margin, so a blink closes from the top down
        f = (k - upper_row) / (lower_row - upper_row)
        sink = 0.0006 + 0.0022 * f
        offset = verts[idx] - centre
        radial = offset / np.linalg.norm(offset, axis=1, keepdims=True)
        tucked = centre + radial * (A.EYE_RADIUS - sink)
        verts[idx] = np.where(inside[:, None], tucked, verts[idx])
        eyelid[idx] = inside
        depth[idx] = np.where(inside, sink, 0.0)

    slit = np.flatnonzero(front & (np.abs(head[mouth_row, :, 0]) < A.MOUTH_HALF_WIDTH))
    return Skin(verts, rows, theta, mouth_row, slit, (upper_row, lower_row), eyelid, depth)


def _mirrored_points(theta, phi):
    """Skin points of the whole grid, casting only the left half (the head is symmetric
    and the column angles are mirrored: φ[C − j] = −φ[j])."""
    half = COLUMNS // 2
    left = _head_points(theta[:, : half + 1], phi[None, : half + 1])
    right = left[:, 1:half][:, ::-1] * np.array([-1.0, 1.0, 1.0])
    return np.concatenate([left, right], 1)


def _bend_rows(theta, anchors):
    """Move anchor rows to their target θ (weighted by a per-column fade) and spread the
    change linearly over the three rows on either side, keeping rows in order."""
    delta = np.zeros_like(theta)
    knots = {}
    for row, (target, fade) in anchors.items():
        knots[row] = (target - theta[row]) * fade
    rows = sorted(knots)
    for c in range(theta.shape[1]):
        ks, vs = [], []
        for r in rows:
            for z in (r - 3, r + 3):
                if z not in knots and 0 <= z < theta.shape[0]:
                    ks.append(z)
                    vs.append(0.0)
            ks.append(r)
            vs.append(knots[r][c])
        order = np.argsort(ks)
        ks, vs = np.asarray(ks)[order], np.asarray(vs)[order]
        keep = np.r_[True, np.diff(ks) > 0]
        delta[:, c] = np.interp(np.arange(theta.shape[0]), ks[keep], vs[keep], left=0, right=0)
    bent = theta + delta
    return (
        np.maximum.accumulate(bent + 1e-4 * np.arange(theta.shape[0])[:, None], 0)
        - 1e-4 * np.arange(theta.shape[0])[:, None]
    )


def _neck_rows(last_head_row, phi):
    """Horizontal rays from the neck axis, from just below the last head row down to the
    neck's open end."""
    start = last_head_row[:, 1] - 0.006
    f = (np.arange(1, NECK_ROWS + 1) / NECK_ROWS)[:, None]
    ys = start[None] + (A.NECK_BOTTOM_Y - start[None]) * f**0.9
    dirs = np.broadcast_to(
        np.stack([np.sin(phi), np.zeros_like(phi), np.cos(phi)], -1), (*ys.shape, 3)
    )
    origins = np.stack([np.zeros_like(ys), ys, np.full_like(ys, A.NECK_AXIS_Z)], -1)
    return origins + cast(origins, dirs, t_max=0.12, steps=20)[..., None] * dirs
