"""The built-in procedural head: FLAME's structure, made from formulas in well under a
second, no files. It is urhead's default head wherever no FLAME file is given.

How it is built (metres, FLAME's frame and joints):

- **Skin**: a grid of rays from inside the head cast onto a signed distance field of
  smoothly blended ellipsoids and capsules (cranium, face, jaw, chin, cheekbones, brow,
  eye sockets and lids, nose, lips, ear bases, neck); rows bend to follow the lid margins
  and the mouth line (:mod:`.surface`). The mouth line is cut open into a lip slit.
- **Parts**: two eyeballs (rotating with the eye joints), two ears, upper and lower teeth
  rows, and a mouth bag (inner lips and oral cavity) stitched to the slit (:mod:`.parts`).
- **Rig**: smooth skinning weights (the lower lip, chin and lower teeth on the jaw),
  joints regressed from nearby vertices, identity and expression blendshapes as smooth
  fields with named leading columns, and pose correctives for the jaw, neck and eyelids
  (:mod:`.rig`).
- **UV**: the skin grid unrolled into the upper 70 % of the square (seam at the back of
  the head; rows and columns are denser over the face, so is the texel density), the parts
  in charts below it.
"""

from __future__ import annotations

import numpy as np

from urhead.head.model import REGION_NAMES, HeadModel
from urhead.head.procedural import anatomy as A
from urhead.head.procedural import parts as P
from urhead.head.procedural import rig as R
from urhead.head.procedural.surface import COLUMNS, build_skin
from urhead.head.uv import seam_free_vertex_uv

NUM_SHAPE = 50
NUM_EXPR = 50
EXPRESSION_NAMES = R.SEMANTIC_EXPRESSIONS
IDENTITY_NAMES = R.SEMANTIC_IDENTITY

_CHARTS = {  # (u0, v0, width, height) in the atlas
    "skin": (0.0, 0.30, 1.0, 0.695),
    "eye_left": (0.005, 0.15, 0.14, 0.14),
    "eye_right": (0.155, 0.15, 0.14, 0.14),
    "ear_left": (0.305, 0.15, 0.14, 0.14),
    "ear_right": (0.455, 0.15, 0.14, 0.14),
    "teeth_upper": (0.605, 0.225, 0.39, 0.065),
    "teeth_lower": (0.605, 0.15, 0.39, 0.065),
    "bag": (0.005, 0.005, 0.99, 0.135),
}


class _Builder:
    """Accumulates vertices, faces and UVs part by part."""

    def __init__(self):
        self.verts, self.faces, self.uv, self.uv_faces, self.region = [], [], [], [], []
        self.nv = self.nt = 0

    def add_verts(self, v, region):
        start = self.nv
        self.verts.append(np.asarray(v, np.float64))
        self.region.append(np.broadcast_to(np.asarray(region, np.int32), (len(v),)))
        self.nv += len(v)
        return start + np.arange(len(v))

    def add_uv(self, uv, chart):
        u0, v0, w, h = _CHARTS[chart]
        start = self.nt
        uv = np.asarray(uv, np.float64)
        self.uv.append(np.stack([u0 + w * uv[:, 0], v0 + h * uv[:, 1]], 1))
        self.nt += len(uv)
        return start + np.arange(len(uv))

    def add_faces(self, faces, uv_faces):
        self.faces.append(np.asarray(faces))
        self.uv_faces.append(np.asarray(uv_faces))

    def add_part(self, part: P.Part, region: str, chart: str):
        ids = self.add_verts(part.verts, REGION_NAMES.index(region))
        uv_ids = self.add_uv(part.uv, chart)
        self.add_faces(ids[part.faces], uv_ids[part.uv_faces])
        return ids


def procedural_head(seed: int = 0) -> HeadModel:
    """The built-in head (about 8k vertices, 16k faces, 50 identity + 50 expression
    columns). ``seed`` draws the small random deformations that fill the blendshape
    columns after the named ones (:data:`IDENTITY_NAMES`, :data:`EXPRESSION_NAMES`); the
    same seed gives the same head, bit for bit."""
    rng = np.random.default_rng(seed)
    skin = build_skin()
    b = _Builder()
    C, rows, m = COLUMNS, skin.rows, skin.mouth_row

    # --- skin grid, crown pole and the lip slit ------------------------------------
    skin_verts = skin.verts.copy()
    slit = skin.slit_columns
    corner_cols = np.array([slit.min() - 1, slit.max() + 1])
    lower_copies = skin_verts[skin.index(m, slit)]  # lips closed at rest: the edges coincide
    grid_ids = b.add_verts(skin_verts, R.skin_regions(skin_verts))
    lower_ids = b.add_verts(lower_copies, R.skin_regions(lower_copies))
    pole = grid_ids[skin.pole]
    u = np.arange(C + 1) / C
    v = 0.995 - 0.99 * (np.arange(rows) + 1) / rows
    grid_uv = b.add_uv(np.stack(np.meshgrid(u, v), -1).reshape(-1, 2), "skin")
    pole_uv = b.add_uv(np.stack([(np.arange(C) + 0.5) / C, np.full(C, 0.995)], 1), "skin")

    def vid(r, c, below=False):
        c = c % C
        if below and r == m:
            hit = np.flatnonzero(slit == c)
            if hit.size:
                return lower_ids[hit[0]]
        return grid_ids[r * C + c]

    faces, uv_faces = [], []
    for r in range(rows - 1):
        for c in range(C):
            a, bb = vid(r, c, below=True), vid(r, c + 1, below=True)
            a2, b2 = vid(r + 1, c), vid(r + 1, c + 1)
            ta, tb = grid_uv[r * (C + 1) + c], grid_uv[r * (C + 1) + c + 1]
            ta2, tb2 = ta + C + 1, tb + C + 1
            faces += [[a, b2, bb], [a, a2, b2]]  # counter-clockwise seen from outside
            uv_faces += [[ta, tb2, tb], [ta, ta2, tb2]]
    for c in range(C):
        faces.append([pole, vid(0, c + 1), vid(0, c)])
        uv_faces.append([pole_uv[c], grid_uv[c + 1], grid_uv[c]])
    b.add_faces(faces, uv_faces)

    # --- parts -----------------------------------------------------------------------
    eye_ids = [
        b.add_part(P.eyeball(s), "eyes", f"eye_{n}") for s, n in ((1, "left"), (-1, "right"))
    ]
    ear_ids = [b.add_part(P.ear(s), "ears", f"ear_{n}") for s, n in ((1, "left"), (-1, "right"))]
    teeth_ids = [
        b.add_part(P.teeth_row(up), "teeth", f"teeth_{n}")
        for up, n in ((True, "upper"), (False, "lower"))
    ]

    # --- mouth bag stitched to the slit ------------------------------------------------
    upper_edge_ids = np.r_[
        vid(m, corner_cols[0]), [vid(m, c) for c in slit], vid(m, corner_cols[1])
    ]
    lower_edge_ids = np.r_[vid(m, corner_cols[0]), lower_ids, vid(m, corner_cols[1])]
    all_verts = np.concatenate(b.verts)
    ring_verts, side, _loop = P.mouth_bag(all_verts[upper_edge_ids], all_verts[lower_edge_ids])
    n = len(upper_edge_ids) - 1
    loop_ids = np.r_[upper_edge_ids, lower_edge_ids[n - 1 : 0 : -1]]
    bag_ids = b.add_verts(ring_verts, REGION_NAMES.index("mouth_interior"))
    L, K = len(loop_ids), len(P.BAG_RINGS)
    rings = [loop_ids] + [bag_ids[k * L : (k + 1) * L] for k in range(K)]
    end = bag_ids[-1]
    bag_u = np.arange(L + 1) / L
    bag_v = 1 - np.arange(K + 1) / (K + 1)
    bag_uv = b.add_uv(np.stack(np.meshgrid(bag_u, bag_v), -1).reshape(-1, 2), "bag")
    end_uv = b.add_uv(np.stack([(np.arange(L) + 0.5) / L, np.zeros(L)], 1), "bag")
    bf, buf = [], []
    for k in range(K):
        for i in range(L):
            a, bb, a2, b2 = (
                rings[k][i],
                rings[k][(i + 1) % L],
                rings[k + 1][i],
                rings[k + 1][(i + 1) % L],
            )
            ta = bag_uv[k * (L + 1) + i]
            tb, ta2, tb2 = ta + 1, ta + L + 1, ta + L + 2
            bf += [[a, bb, b2], [a, b2, a2]]
            buf += [[ta, tb, tb2], [ta, tb2, ta2]]
    for i in range(L):
        bf.append([rings[K][i], rings[K][(i + 1) % L], end])
        t = bag_uv[K * (L + 1) + i]
        buf.append([t, t + 1, end_uv[i]])
    bf, buf = np.asarray(bf), np.asarray(buf)
    # the bag is seen from inside: wind its faces towards the cavity's axis
    verts = np.concatenate(b.verts)
    p = verts[bf]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    axis_pt = np.stack([0 * p[:, 0, 0], np.full(len(p), A.MOUTH_Y), p.mean(1)[:, 2]], 1)
    if np.einsum("fc,fc->", normal, axis_pt - p.mean(1)) < 0:
        bf, buf = bf[:, [0, 2, 1]], buf[:, [0, 2, 1]]
    b.add_faces(bf, buf)

    verts = np.concatenate(b.verts)
    faces = np.concatenate(b.faces)
    uv_coords = np.clip(np.concatenate(b.uv), 0, 1)
    uv_faces = np.concatenate(b.uv_faces)
    region = np.concatenate(b.region)
    V = len(verts)

    # --- skinning ----------------------------------------------------------------------
    skin_ids = np.r_[grid_ids, lower_ids]
    below = np.zeros(V)
    below[lower_ids] = 1
    row_of = np.full(V, -100)
    row_of[grid_ids[: rows * C]] = np.repeat(np.arange(rows), C)
    row_of[lower_ids] = m
    col_x = np.abs(verts[:, 0])
    near_slit = np.clip(1 - (col_x - A.MOUTH_HALF_WIDTH) / 0.006, 0, 1) * (verts[:, 2] > 0.06)
    below[grid_ids[: rows * C]] = (row_of[grid_ids[: rows * C]] > m).astype(float)
    slit_lip = near_slit * np.clip(1 - (np.abs(row_of - m) - 2) / 3, 0, 1)
    weights = np.zeros((V, 5))
    weights[skin_ids] = R.skin_weights(verts[skin_ids], below[skin_ids], slit_lip[skin_ids])
    weights[eye_ids[0], R.LEFT_EYE] = 1
    weights[eye_ids[1], R.RIGHT_EYE] = 1
    for ids in ear_ids:
        weights[ids, R.NECK] = 1
    weights[teeth_ids[0], R.NECK] = 1
    weights[teeth_ids[1], R.JAW] = 1
    ring_side = np.r_[np.tile(side, K), 0.0]
    weights[bag_ids, R.JAW] = (1 - ring_side) / 2
    weights[bag_ids, R.NECK] = (1 + ring_side) / 2

    # --- joint regressor -----------------------------------------------------------------
    regressor = np.zeros((5, V))
    regressor[R.LEFT_EYE, eye_ids[0]] = R.min_norm_regressor(verts[eye_ids[0]], A.JOINTS[3])
    regressor[R.RIGHT_EYE, eye_ids[1]] = R.min_norm_regressor(verts[eye_ids[1]], A.JOINTS[4])
    grid = grid_ids[: rows * C]
    for j in (R.ROOT, R.NECK, R.JAW):
        d = np.linalg.norm((verts[grid] - A.JOINTS[j]) * np.array([0.3, 1, 0.3]), axis=1)
        near = grid[np.argsort(d)[:24]]
        regressor[j, near] = R.min_norm_regressor(verts[near], A.JOINTS[j])

    # --- blendshapes -----------------------------------------------------------------------
    shapedirs = np.zeros((V, 3, NUM_SHAPE + NUM_EXPR))
    rigid = [eye_ids[0], eye_ids[1]]
    for k, name in enumerate(IDENTITY_NAMES):
        shapedirs[:, :, k] = _rigid_parts(R.identity_field(name, verts), verts, rigid)
    filler = R.random_fields(
        verts,
        NUM_SHAPE - len(IDENTITY_NAMES),
        rng,
        0.004,
        ([-0.08, -0.2, -0.1], [0.08, 0.14, 0.11]),
    )
    for k in range(filler.shape[2]):
        shapedirs[:, :, len(IDENTITY_NAMES) + k] = _rigid_parts(filler[:, :, k], verts, rigid)
    skin_mask = np.zeros(V)
    skin_mask[skin_ids] = 1
    bag_fade = np.zeros(V)
    bag_fade[bag_ids] = np.r_[np.repeat([0.8, 0.5, 0.25, 0.1, 0, 0, 0], L), 0]
    expr_mask = (skin_mask + bag_fade)[:, None]  # the fields are local; rigid parts stay
    blink_left, blink_right = _blink(verts, skin, grid_ids)
    for k, name in enumerate(EXPRESSION_NAMES):
        col = NUM_SHAPE + k
        if name == "blink":
            shapedirs[:, :, col] = blink_left + blink_right
        elif name == "blink_left":
            shapedirs[:, :, col] = blink_left
        elif name == "blink_right":
            shapedirs[:, :, col] = blink_right
        else:
            shapedirs[:, :, col] = R.EXPRESSION_FIELDS[name](verts) * expr_mask
    filler = R.random_fields(
        verts,
        NUM_EXPR - len(EXPRESSION_NAMES),
        rng,
        0.0025,
        ([-0.05, A.MOUTH_Y - 0.04, 0.05], [0.05, A.EYE_Y + 0.04, 0.1]),
    )
    for k in range(filler.shape[2]):
        shapedirs[:, :, NUM_SHAPE + len(EXPRESSION_NAMES) + k] = filler[:, :, k] * expr_mask

    return HeadModel(
        v_template=verts,
        faces=faces,
        shapedirs=shapedirs,
        posedirs=_pose_correctives(verts, skin_mask, region),
        j_regressor=regressor,
        parents=np.array([-1, 0, 1, 1, 1]),
        lbs_weights=weights,
        uv_coords=uv_coords,
        uv_faces=uv_faces,
        vertex_uv=seam_free_vertex_uv(faces, uv_faces, uv_coords, V),
        vertex_region=region,
        num_shape=NUM_SHAPE,
        num_expr=NUM_EXPR,
    )


def _rigid_parts(field, verts, groups):
    """Eyeballs move rigidly under identity changes: each takes the mean displacement of
    its vertices."""
    field = field.copy()
    for ids in groups:
        field[ids] = field[ids].mean(0)
    return field


def _blink(verts, skin, grid_ids):
    """Per-eye blink: the skin tucked between the lid margins comes out to 1.2 mm over the
    eyeball; deeper rows travel further, so the lid closes from the top down. The upper lid
    above the margin slides down a little with it."""
    out = []
    upper, _lower = skin.lid_rows
    for s, centre in ((1, A.JOINTS[3]), (-1, A.JOINTS[4])):
        d = np.zeros_like(verts)
        ids = grid_ids[np.flatnonzero(skin.eyelid)]
        ids = ids[np.sign(verts[ids, 0]) == s]
        offset = verts[ids] - centre
        radial = offset / np.linalg.norm(offset, axis=1, keepdims=True)
        d[ids] = radial * (skin.eyelid_depth[ids - grid_ids[0]] + 0.0012)[:, None]
        d[ids, 1] -= 0.0015
        margin = grid_ids[skin.index(upper, np.arange(COLUMNS))]
        margin = margin[
            (np.sign(verts[margin, 0]) == s)
            & (np.abs(np.abs(verts[margin, 0]) - A.EYE_X) < 0.015)
            & (verts[margin, 2] > 0.05)
        ]
        d[margin, 1] -= 0.0018
        d[margin, 2] += 0.0008
        out.append(d)
    return out


def _pose_correctives(verts, skin_mask, region):
    """(36, 3V): jaw opening fills the cheeks out a little, bending the neck forward
    bunches the skin under the chin, and the upper lids follow the eyes' pitch."""
    V = len(verts)
    posedirs = np.zeros((4, 3, 3, V, 3))  # joint (neck, jaw, eyes), row, col, vertex, xyz
    # (R − I)[2, 1] ≈ sin(angle) for a rotation about x (the jaw opening, a nod)
    cheeks = np.zeros((V, 3))
    for s in (1.0, -1.0):
        w = R._bump(verts, [s * 0.045, A.MOUTH_Y + 0.005, 0.045], (0.015, 0.02, 0.03))
        cheeks += w[:, None] * np.array([s * 0.006, 0.002, 0.0])
    posedirs[R.JAW - 1, 2, 1] = cheeks * skin_mask[:, None]
    chin = R._bump(verts, [0, A.CHIN_Y - 0.02, 0.04], (0.03, 0.02, 0.03))
    posedirs[R.NECK - 1, 2, 1] = chin[:, None] * np.array([0, -0.004, 0.008]) * skin_mask[:, None]
    for joint, s in ((R.LEFT_EYE, 1.0), (R.RIGHT_EYE, -1.0)):
        lid = R._bump(verts, [s * A.EYE_X, A.EYE_Y + 0.007, A.EYE_Z + 0.012], (0.012, 0.004, 0.008))
        lid *= (np.sign(verts[:, 0]) == s) * skin_mask * (region != REGION_NAMES.index("scalp"))
        # (R − I)[1, 2] = −sin(pitch): looking down lowers the lid
        posedirs[joint - 1, 1, 2] = lid[:, None] * np.array([0, 0.006, 0])
    return posedirs.reshape(36, V * 3)
