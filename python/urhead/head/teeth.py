"""The teeth extension of VHAP / GaussianAvatars for FLAME, with URHead's two fixes.

VHAP adds two rows of teeth to FLAME (+120 vertices → 5143, +168 faces → 10144), built
from the lip vertices of the template; the tracked ``static_offset (1, 5143, 3)`` of their
datasets assumes exactly this vertex layout, so we reproduce its vertex order and rest
geometry. Each row is a U-shaped band (front, biting edge, back) sampled at 15 points
across the mouth; in vertex order the 8 rows of 15 are: upper root, lower root, upper
edge, lower edge, upper root (back), upper edge (back), lower root (back), lower edge
(back). The upper teeth are skinned to the neck joint (they move with the skull), the
lower ones to the jaw. Identity blendshapes are the mean of the two lip rings', expression
and pose correctives are zero, and the joint regressor ignores them.

URHead's supplement ("VHAP Modification") changes two things, and so do we:

1. Teeth UVs re-laid so the two rows never overlap in UV: each row is unrolled into its
   own band (one UV per vertex, arc-length spaced along the mouth, row spacing by the
   band's 3D heights), inside a box of the UV square the FLAME layout leaves empty
   (checked against the existing layout when the extension is added).
2. A mouth plate behind the teeth, so the back of the head never shows through an open
   mouth: a strip of 28 triangles between the upper and lower back-root rows (it adds no
   vertex, so ``static_offset`` still fits; it opens with the jaw), with its own UV band.

The lip rings are given by FLAME vertex ids (VHAP's ``lip_outside_ring_upper/lower``,
ordered corner to corner); pass others in :class:`TeethConfig` for another topology.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from urhead.errors import IndexRangeError, InvalidArgumentError
from urhead.head.model import REGION_NAMES, HeadModel
from urhead.head.uv import seam_free_vertex_uv

FLAME_LIP_OUTSIDE_UPPER = (
    1713, 1715, 1716, 1735, 1696, 1694, 1657, 3543, 2774, 2811, 2813, 2850, 2833, 2832, 2830,
)  # fmt: skip
"""FLAME vertex ids of the upper lip's outer ring, corner to corner (VHAP's ring)."""
FLAME_LIP_OUTSIDE_LOWER = (
    1576, 1577, 1773, 1774, 1795, 1802, 1865, 3503, 2948, 2905, 2898, 2881, 2880, 2713, 2712,
)  # fmt: skip
"""FLAME vertex ids of the lower lip's outer ring, paired with the upper ring's."""

NECK_JOINT, JAW_JOINT = 1, 2


@dataclass(frozen=True)
class TeethConfig:
    """Where and how the teeth are built. Lengths are in units of ``d``, the mean distance
    between paired upper and lower lip vertices (VHAP's construction)."""

    upper_lip_ids: tuple[int, ...] = FLAME_LIP_OUTSIDE_UPPER
    lower_lip_ids: tuple[int, ...] = FLAME_LIP_OUTSIDE_LOWER
    depth: float = 1.5
    """Teeth front plane behind the lips' midpoints."""
    gap: float = 0.1
    """Each biting edge's distance from the mid-plane."""
    height: float = 2.0
    """Edge-to-root height of each row."""
    lower_setback: float = 0.4
    """The lower row sits this much behind the upper (overbite)."""
    thickness: float = 1.0
    """Front-to-back thickness of each row."""
    mouth_plate: bool = True
    uv_box: tuple[float, float, float, float] = (0.38, 0.9575, 0.62, 0.9917)
    """(u0, v0, u1, v1): the empty part of FLAME's UV square the teeth are laid into."""


TEETH_ROWS_PER_SIDE = 4
ROW_ORDER = (
    "upper_root",
    "lower_root",
    "upper_edge",
    "lower_edge",
    "upper_root_back",
    "upper_edge_back",
    "lower_root_back",
    "lower_edge_back",
)
"""The order of the 8 rows of teeth vertices (VHAP's, so static offsets line up)."""


def teeth_rest_geometry(v_template: np.ndarray, config: TeethConfig) -> dict[str, np.ndarray]:
    """Rest positions of the 8 rows, each (n, 3) with n lip pairs, keyed by ROW_ORDER."""
    upper, lower = _lip_rings(v_template, config)
    d = float(np.linalg.norm(upper - lower, axis=1).mean())
    up, back = np.array([0.0, d, 0.0]), np.array([0.0, 0.0, d])
    middle = (upper + lower) / 2
    middle[:, 1] = middle[:, 1].mean()
    middle[:, 2] -= config.depth * d
    rows = {
        "upper_edge": middle + config.gap * up,
        "lower_edge": middle - config.gap * up - config.lower_setback * back,
    }
    rows["upper_root"] = rows["upper_edge"] + config.height * up
    rows["lower_root"] = rows["lower_edge"] - config.height * up
    for name in ("upper_root", "upper_edge", "lower_root", "lower_edge"):
        rows[name + "_back"] = rows[name] - config.thickness * back
    return rows


def add_teeth(head: HeadModel, config: TeethConfig = TeethConfig()) -> HeadModel:
    """``head`` with the teeth rows (and, by default, the mouth plate) appended after its
    vertices and faces. FLAME: 5023 → 5143 vertices, 9976 → 10144 faces (+28 with the
    mouth plate). Requires the FLAME joints (neck 1, jaw 2)."""
    if head.num_joints <= JAW_JOINT:
        raise InvalidArgumentError(f"teeth need the neck and jaw joints, head has {head.parents}")
    rows = teeth_rest_geometry(head.v_template, config)
    n = len(config.upper_lip_ids)
    V, J = head.num_vertices, head.num_joints
    ids = {name: V + k * n + np.arange(n) for k, name in enumerate(ROW_ORDER)}
    new_verts = np.concatenate([rows[name] for name in ROW_ORDER])
    positions = np.concatenate([head.v_template, new_verts])

    strips = _teeth_strips(config.mouth_plate)
    flips = [_needs_flip(_quad_strip(ids[a], ids[b]), positions, out) for a, b, out, _ in strips]
    new_faces = np.concatenate(
        [
            _oriented(_quad_strip(ids[a], ids[b]), f)
            for (a, b, _, _), f in zip(strips, flips, strict=True)
        ]
    )

    upper_ids = np.asarray(config.upper_lip_ids)
    lower_ids = np.asarray(config.lower_lip_ids)
    lip_mean = (head.shapedirs[upper_ids] + head.shapedirs[lower_ids]) / 2  # (n, 3, NB)
    teeth_dirs = np.tile(lip_mean, (len(ROW_ORDER), 1, 1))
    teeth_dirs[:, :, head.num_shape :] = 0  # expressions leave the teeth alone

    weights = np.zeros((len(new_verts), J), np.float32)
    upper_rows = [k for k, name in enumerate(ROW_ORDER) if name.startswith("upper")]
    for k in range(len(ROW_ORDER)):
        weights[k * n : (k + 1) * n, NECK_JOINT if k in upper_rows else JAW_JOINT] = 1

    posedirs = head.posedirs.reshape(head.posedirs.shape[0], V, 3)
    posedirs = np.concatenate([posedirs, np.zeros((posedirs.shape[0], len(new_verts), 3))], 1)

    all_faces = np.concatenate([head.faces, new_faces])
    uv_coords, uv_faces, vertex_uv = head.uv_coords, head.uv_faces, head.vertex_uv
    if head.has_uv:
        uv_coords, new_uv_faces = _teeth_uv(head, rows, strips, flips, config, n)
        uv_faces = np.concatenate([head.uv_faces, new_uv_faces])
        vertex_uv = seam_free_vertex_uv(all_faces, uv_faces, uv_coords, len(positions))

    return HeadModel(
        v_template=positions,
        faces=all_faces,
        shapedirs=np.concatenate([head.shapedirs, teeth_dirs]),
        posedirs=posedirs.reshape(posedirs.shape[0], -1),
        j_regressor=np.concatenate([head.j_regressor, np.zeros((J, len(new_verts)))], 1),
        parents=head.parents,
        lbs_weights=np.concatenate([head.lbs_weights, weights]),
        uv_coords=uv_coords,
        uv_faces=uv_faces,
        vertex_uv=vertex_uv,
        vertex_region=np.concatenate(
            [head.vertex_region, np.full(len(new_verts), REGION_NAMES.index("teeth"))]
        ),
        num_shape=head.num_shape,
        num_expr=head.num_expr,
    )


def _lip_rings(v_template, config):
    upper = np.asarray(config.upper_lip_ids, np.int64)
    lower = np.asarray(config.lower_lip_ids, np.int64)
    if upper.ndim != 1 or upper.shape != lower.shape or upper.size < 2:
        raise InvalidArgumentError(
            "upper_lip_ids and lower_lip_ids must be equally long lists of ≥ 2 vertex ids, "
            f"got {upper.size} and {lower.size}"
        )
    V = v_template.shape[0]
    for name, ids in (("upper_lip_ids", upper), ("lower_lip_ids", lower)):
        if ids.min() < 0 or ids.max() >= V:
            raise IndexRangeError(f"{name} must index the template's {V} vertices")
    return v_template[upper].astype(np.float64), v_template[lower].astype(np.float64)


def _teeth_strips(mouth_plate: bool):
    """(row a, row b, outward direction, UV band) for each strip of triangles."""
    y, z = np.array([0.0, 1, 0]), np.array([0.0, 0, 1])
    strips = [
        ("upper_root", "upper_edge", z, "upper"),
        ("upper_root_back", "upper_edge_back", -z, "upper"),
        ("upper_edge", "upper_edge_back", -y, "upper"),
        ("lower_root", "lower_edge", z, "lower"),
        ("lower_root_back", "lower_edge_back", -z, "lower"),
        ("lower_edge", "lower_edge_back", y, "lower"),
    ]
    if mouth_plate:
        strips.append(("upper_root_back", "lower_root_back", z, "plate"))
    return strips


def _quad_strip(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """2(n − 1) triangles between two rows of n indices."""
    a0, a1, b0, b1 = a[:-1], a[1:], b[:-1], b[1:]
    return np.stack([np.stack([a0, a1, b1], 1), np.stack([a0, b1, b0], 1)], 1).reshape(-1, 3)


def _needs_flip(tris: np.ndarray, positions: np.ndarray, outward: np.ndarray) -> bool:
    """Whether the strip's summed normal points against ``outward`` (the lip rings may run
    either way across the mouth)."""
    p = positions[tris]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(0)
    return bool(normal @ outward < 0)


def _oriented(tris: np.ndarray, flip: bool) -> np.ndarray:
    return tris[:, [0, 2, 1]] if flip else tris


def _teeth_uv(head, rows, strips, flips, config, n):
    """UV coordinates appended for the teeth bands (one UV per teeth vertex, so the layout
    is seam-free there) and a separate band for the mouth plate; returns the new
    ``uv_coords`` and the teeth's ``uv_faces``, wound like their 3D faces."""
    u0, v0, u1, v1 = config.uv_box
    if not (0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1):
        raise InvalidArgumentError(
            f"uv_box must be (u0, v0, u1, v1) inside [0, 1]², got {config.uv_box}"
        )
    overlapping = _triangles_touch_box(head.uv_coords[head.uv_faces], config.uv_box)
    if overlapping.any():
        raise InvalidArgumentError(
            f"teeth uv_box {config.uv_box} overlaps {int(overlapping.sum())} UV triangles of "
            f"the head (first: face {int(np.flatnonzero(overlapping)[0])}); choose an empty box"
        )
    middle = (rows["upper_edge"] + rows["lower_edge"]) / 2
    arc = np.r_[0, np.cumsum(np.linalg.norm(np.diff(middle, axis=0), axis=1))]
    margin = 0.02 * (u1 - u0)
    u = u0 + margin + (u1 - u0 - 2 * margin) * arc / arc[-1]
    height = v1 - v0
    gap = 0.04 * height
    bands = {  # (top, bottom) of each band
        "upper": (v1 - gap, v1 - 0.42 * height),
        "lower": (v1 - 0.46 * height, v1 - 0.84 * height),
        "plate": (v1 - 0.88 * height, v0 + gap),
    }
    h, t = config.height, config.thickness
    fractions = np.array([0.0, h, h + t, 2 * h + t]) / (2 * h + t)

    def band_rows(names, band):
        top, bottom = bands[band]
        f = fractions if len(names) == 4 else np.array([0.0, 1.0])
        return {
            name: np.stack([u, np.full(n, top + (bottom - top) * fk)], 1)
            for name, fk in zip(names, f, strict=True)
        }

    teeth_uv = {}
    teeth_uv.update(
        band_rows(["upper_root", "upper_edge", "upper_edge_back", "upper_root_back"], "upper")
    )
    teeth_uv.update(
        band_rows(["lower_root", "lower_edge", "lower_edge_back", "lower_root_back"], "lower")
    )
    T = head.uv_coords.shape[0]
    uv_ids = {name: T + k * n + np.arange(n) for k, name in enumerate(ROW_ORDER)}
    new_uv = [teeth_uv[name] for name in ROW_ORDER]
    if config.mouth_plate:
        plate = band_rows(["plate_upper", "plate_lower"], "plate")
        base = T + len(ROW_ORDER) * n
        uv_ids["plate_upper"], uv_ids["plate_lower"] = base + np.arange(n), base + n + np.arange(n)
        new_uv += [plate["plate_upper"], plate["plate_lower"]]
    uv_faces = []
    for (a, b, _, band), flip in zip(strips, flips, strict=True):
        if band == "plate":
            a, b = "plate_upper", "plate_lower"
        uv_faces.append(_oriented(_quad_strip(uv_ids[a], uv_ids[b]), flip))
    uv_coords = np.concatenate([head.uv_coords, *new_uv])
    return uv_coords, np.concatenate(uv_faces)


def _triangles_touch_box(tri: np.ndarray, box) -> np.ndarray:
    """(F,) bool: which UV triangles (F, 3, 2) intersect the closed box (u0, v0, u1, v1)
    (separating-axis test: the box's two axes and the three triangle edge normals)."""
    u0, v0, u1, v1 = box
    lo, hi = tri.min(1), tri.max(1)
    touch = (lo[:, 0] <= u1) & (hi[:, 0] >= u0) & (lo[:, 1] <= v1) & (hi[:, 1] >= v0)
    corners = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
    for k in range(3):
        edge = tri[:, (k + 1) % 3] - tri[:, k]
        normal = np.stack([-edge[:, 1], edge[:, 0]], 1)
        t_proj = np.einsum("fc,fkc->fk", normal, tri)
        b_proj = normal @ corners.T
        separated = (b_proj.max(1) < t_proj.min(1)) | (b_proj.min(1) > t_proj.max(1))
        touch &= ~separated
    return touch
