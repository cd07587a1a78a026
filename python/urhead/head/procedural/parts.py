"""Separate parts of the built-in head: eyeballs, ears, teeth and the mouth bag.

Each part returns its vertices, faces (counter-clockwise seen from where it is meant to be
seen) and its own UV chart in the unit square (placed into the atlas by the caller).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from urhead.head.procedural import anatomy as A


@dataclass(frozen=True)
class Part:
    verts: np.ndarray  # (n, 3)
    faces: np.ndarray  # (m, 3) local vertex indices
    uv: np.ndarray  # (t, 2) chart coordinates in [0, 1]²
    uv_faces: np.ndarray  # (m, 3) local uv indices


def polar_sphere(rings: int, cols: int) -> Part:
    """A unit sphere with its poles on ±z: front pole, ``rings`` rings, back pole. UV: a
    polar disc, front pole in the centre; the back pole gets one UV per triangle on the rim."""
    alpha = np.linspace(0, np.pi, rings + 2)[1:-1]
    beta = np.linspace(0, 2 * np.pi, cols, endpoint=False)
    a, b = np.meshgrid(alpha, beta, indexing="ij")
    ring = np.stack([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]])
    back = len(verts) - 1

    def vid(r, c):
        return 1 + r * cols + c % cols

    faces = [[0, vid(0, c), vid(0, c + 1)] for c in range(cols)]
    for r in range(rings - 1):
        for c in range(cols):
            faces += [
                [vid(r, c), vid(r + 1, c), vid(r + 1, c + 1)],
                [vid(r, c), vid(r + 1, c + 1), vid(r, c + 1)],
            ]
    faces += [[vid(rings - 1, c), back, vid(rings - 1, c + 1)] for c in range(cols)]
    # UV: radius ∝ polar angle; a seam column (cols + 1 UVs per ring)
    bu = np.linspace(0, 2 * np.pi, cols + 1)
    rad = 0.48 * np.r_[alpha, np.pi] / np.pi
    uv = [[0.5, 0.5]]
    for rr in rad[:-1]:
        uv += [[0.5 + rr * np.cos(t), 0.5 + rr * np.sin(t)] for t in bu]
    rim = [
        [0.5 + 0.48 * np.cos(t + np.pi / cols), 0.5 + 0.48 * np.sin(t + np.pi / cols)]
        for t in bu[:-1]
    ]
    uv += rim

    def tid(r, c):
        return 1 + r * (cols + 1) + c

    rim0 = 1 + rings * (cols + 1)
    uv_faces = [[0, tid(0, c), tid(0, c + 1)] for c in range(cols)]
    for r in range(rings - 1):
        for c in range(cols):
            uv_faces += [
                [tid(r, c), tid(r + 1, c), tid(r + 1, c + 1)],
                [tid(r, c), tid(r + 1, c + 1), tid(r, c + 1)],
            ]
    uv_faces += [[tid(rings - 1, c), rim0 + c, tid(rings - 1, c + 1)] for c in range(cols)]
    faces = np.asarray(faces)
    # wind outwards
    p = verts[faces]
    if np.einsum("fc,fc->", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p.mean(1)) < 0:
        faces, uv_faces = faces[:, [0, 2, 1]], np.asarray(uv_faces)[:, [0, 2, 1]]
    return Part(verts, faces, np.asarray(uv), np.asarray(uv_faces))


def eyeball(side: int) -> Part:
    """``side`` +1 (left, +x) or −1. Radius 12 mm with a 1 mm corneal bulge at the front."""
    s = polar_sphere(12, 20)
    bulge = 0.0011 * np.clip(1 - np.arccos(np.clip(s.verts[:, 2], -1, 1)) / 0.55, 0, 1) ** 2
    centre = np.array([side * A.EYE_X, A.EYE_Y, A.EYE_Z])
    return Part(centre + s.verts * (A.EYE_RADIUS + bulge)[:, None], s.faces, s.uv, s.uv_faces)


def ear(side: int) -> Part:
    """A flattened shell facing outwards, rim raised and bowl (concha) pressed in, tilted
    back; its inner face is sunk into the head."""
    s = polar_sphere(9, 18)
    u = s.verts.copy()  # poles on ±z: z becomes the outward normal of the ear
    r = np.linalg.norm(u[:, :2], axis=1)
    outer = u[:, 2] > 0
    bowl = np.where(outer, -0.55 * np.exp(-(((r - 0.25) / 0.35) ** 2)), 0.0)
    rim = np.where(outer, 0.35 * np.exp(-(((r - 0.92) / 0.12) ** 2)), 0.0)
    local = np.stack([u[:, 0] * 0.0175, u[:, 1] * 0.030, (u[:, 2] + bowl + rim) * 0.0055], 1)
    local[:, 0] += 0.003 * (u[:, 1] > 0) * u[:, 1]  # wider at the top
    tilt, flare = np.deg2rad(-12), np.deg2rad(22)
    rot_x = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    # ear frame: x → back (−z), y → up, z (normal) → outward, flared towards the front
    frame = np.array([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]]).T
    c, sn = np.cos(flare), np.sin(flare)
    flare_m = np.array([[c, 0, sn], [0, 1, 0], [-sn, 0, c]])
    world = local @ rot_x.T @ frame.T @ flare_m.T
    centre = np.array([0.079, A.EYE_Y - 0.010, -0.026])
    verts = world + centre
    faces = s.faces
    if side < 0:
        verts = verts * np.array([-1.0, 1, 1])
        faces = faces[:, [0, 2, 1]]
        return Part(verts, faces, s.uv, s.uv_faces[:, [0, 2, 1]])
    return Part(verts, faces, s.uv, s.uv_faces)


TEETH_COLUMNS = 17


def teeth_row(upper: bool) -> Part:
    """A row of teeth as a closed band along the dental arch: front, biting edge, back and
    root strips (4 rows of 17 vertices, unrolled to a UV band)."""
    x = np.linspace(-0.0235, 0.0235, TEETH_COLUMNS)
    front_z = 0.0795 - 15.0 * x**2 - (0 if upper else 0.0068)
    sign = 1.0 if upper else -1.0
    edge_y = A.MOUTH_Y + (-0.0006 if upper else 0.0004)
    root_y = edge_y + sign * (0.0105 if upper else 0.0092)
    thick = 0.0058
    rows = [
        np.stack([x, np.full_like(x, root_y), front_z], 1),
        np.stack([x, np.full_like(x, edge_y), front_z + 0.0004], 1),
        np.stack([x * 0.97, np.full_like(x, edge_y), front_z - thick], 1),
        np.stack([x * 0.97, np.full_like(x, root_y), front_z - thick], 1),
    ]
    verts = np.concatenate(rows)
    n = TEETH_COLUMNS
    faces = []
    for r in range(4):
        a, b = r * n, ((r + 1) % 4) * n
        for c in range(n - 1):
            faces += [[a + c, b + c, b + c + 1], [a + c, b + c + 1, a + c + 1]]
    faces = np.asarray(faces)
    uv_rows = np.linspace(0.95, 0.05, 5)
    uv = np.concatenate([np.stack([np.linspace(0.02, 0.98, n), np.full(n, v)], 1) for v in uv_rows])
    uv_faces = []
    for r in range(4):
        a, b = r * n, (r + 1) * n
        for c in range(n - 1):
            uv_faces += [[a + c, b + c, b + c + 1], [a + c, b + c + 1, a + c + 1]]
    uv_faces = np.asarray(uv_faces)
    p = verts[faces[: 2 * (n - 1)]]  # the front strip must face out of the mouth (+z)
    if np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(0)[2] < 0:
        faces, uv_faces = faces[:, [0, 2, 1]], uv_faces[:, [0, 2, 1]]
    return Part(verts, faces, uv, uv_faces)


BAG_RINGS = (  # (depth behind the lips, half-height, width factor) of each ring
    (0.0035, 0.0040, 0.97),
    (0.0085, 0.0085, 0.98),
    (0.0160, 0.0150, 1.05),
    (0.0260, 0.0175, 1.10),
    (0.0380, 0.0160, 0.95),
    (0.0480, 0.0120, 0.70),
    (0.0550, 0.0070, 0.40),
)
BAG_END_DEPTH = 0.058


def mouth_bag(
    upper_edge: np.ndarray, lower_edge: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The inner lips and the oral cavity behind the lip slit.

    ``upper_edge`` / ``lower_edge`` (n + 1, 3): the slit's two edges, corner to corner
    (sharing the corners). Returns the ring vertices (K·2n, 3) then the closing point, the
    side of each (+1 upper, −1 lower, 0 corner), and the loop of slit vertices in order
    (indices into the edges: positive = upper[i], negative = lower[−i])."""
    n = len(upper_edge) - 1
    loop = np.concatenate([upper_edge[: n + 1], lower_edge[n - 1 : 0 : -1]])
    side = np.r_[0, np.ones(n - 1), 0, -np.ones(n - 1)]
    half_w = np.abs(upper_edge[[0, n], 0]).max()
    x = loop[:, 0]
    profile = np.clip(1 - (np.abs(x) / half_w) ** 2.5, 0, 1) ** 0.5
    rings = []
    for depth, h, w in BAG_RINGS:
        rx = x * w
        ry = A.MOUTH_Y + side * h * profile
        rz = loop[:, 2] - depth - 10.0 * (rx**2 - x**2).clip(0)
        rings.append(np.stack([rx, ry, rz], 1))
    end = np.array([[0.0, A.MOUTH_Y, loop[:, 2].max() - BAG_END_DEPTH]])
    return np.concatenate([*rings, end]), side, loop
