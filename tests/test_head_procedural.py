"""The built-in procedural head: FLAME's structure, human proportions, a rig that moves
like a head, and a mesh that stays well-formed at extreme poses and expressions."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.csgraph
import torch

from urhead.head import (
    REGION_NAMES,
    HeadModel,
    load_head,
    procedural_head,
    save_head,
    uv_region_masks,
)
from urhead.head.procedural import EXPRESSION_NAMES, IDENTITY_NAMES, NUM_EXPR, NUM_SHAPE
from urhead.head.procedural import anatomy as A
from urhead.ops._reference import axis_angle_to_matrix


@pytest.fixture(scope="module")
def head() -> HeadModel:
    return procedural_head()


def _expr(name, value=1.0, batch=1):
    e = torch.zeros(batch, NUM_EXPR, dtype=torch.float64)
    e[:, EXPRESSION_NAMES.index(name)] = value
    return e


def _pose(**joints):
    p = torch.zeros(1, 15, dtype=torch.float64)
    slots = {"glob": 0, "neck": 3, "jaw": 6, "leye": 9, "reye": 12}
    for k, v in joints.items():
        p[0, slots[k] : slots[k] + 3] = torch.tensor(v, dtype=torch.float64)
    return p


def _face_areas(verts, faces):
    p = verts[faces]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def test_flame_structure(head):
    assert head.parents.tolist() == [-1, 0, 1, 1, 1]
    assert (head.num_shape, head.num_expr) == (NUM_SHAPE, NUM_EXPR)
    V = head.num_vertices
    assert 4000 < V < 10000
    assert head.shapedirs.shape == (V, 3, NUM_SHAPE + NUM_EXPR)
    assert head.posedirs.shape == (36, 3 * V)
    assert head.j_regressor.shape == (5, V)
    for name in ("v_template", "shapedirs", "posedirs", "j_regressor", "lbs_weights", "uv_coords"):
        assert getattr(head, name).dtype == np.float32, name
    assert head.faces.dtype == np.int32 and head.uv_faces.dtype == np.int32
    assert head.lbs_weights.min() >= 0
    np.testing.assert_allclose(head.lbs_weights.sum(1), 1, atol=1e-6)
    assert head.faces.min() >= 0 and head.faces.max() < V
    assert np.unique(head.faces).size == V  # every vertex is used
    assert head.uv_coords.min() >= 0 and head.uv_coords.max() <= 1
    for r in range(len(REGION_NAMES)):
        assert np.any(head.vertex_region == r), REGION_NAMES[r]


def test_vertex_uv_is_the_first_occurrence(head):
    flat_v, flat_t = head.faces.ravel(), head.uv_faces.ravel()
    _, first = np.unique(flat_v, return_index=True)
    np.testing.assert_array_equal(head.vertex_uv, head.uv_coords[flat_t[first]])


def test_uv_layout_has_no_degenerate_triangles_and_masks_cover_regions(head):
    tri = head.uv_coords[head.uv_faces].astype(np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert area.min() > 1e-9
    masks = uv_region_masks(head, 256)
    for name, mask in masks.items():
        assert mask.any(), name
    assert masks["face"].sum() > masks["ears"].sum()


def test_human_proportions(head):
    v = head.v_template
    joints = head.j_regressor @ v
    assert joints[3, 0] - joints[4, 0] == pytest.approx(0.063, abs=1e-4)
    skin = np.isin(head.vertex_region, [0, 1, 5])
    height = v[skin, 1].max() - v[skin, 1].min()
    assert 0.21 < height < 0.25
    width = v[:, 0].max() - v[:, 0].min()  # across the ears
    assert 0.15 < width < 0.2
    nose_tip = v[np.argmax(v[:, 2])]
    assert abs(nose_tip[0]) < 1e-3 and A.MOUTH_Y < nose_tip[1] < A.EYE_Y


def test_joints_match_the_anatomy(head):
    np.testing.assert_allclose(head.j_regressor @ head.v_template, A.JOINTS, atol=1e-5)


def test_deterministic_and_seeded():
    a, b = procedural_head(0), procedural_head(0)
    for name in HeadModel.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    c = procedural_head(1)
    named = len(IDENTITY_NAMES)
    np.testing.assert_array_equal(a.shapedirs[:, :, :named], c.shapedirs[:, :, :named])
    assert not np.array_equal(
        a.shapedirs[:, :, named:NUM_SHAPE], c.shapedirs[:, :, named:NUM_SHAPE]
    )
    np.testing.assert_array_equal(a.v_template, c.v_template)


def test_npz_round_trip(head, tmp_path):
    save_head(head, tmp_path / "head.npz")
    again = load_head(tmp_path / "head.npz")
    for name in HeadModel.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(again, name), getattr(head, name), err_msg=name)


def test_eyes_rotate_with_the_eye_joints(head):
    left = np.flatnonzero(
        (head.vertex_region == REGION_NAMES.index("eyes")) & (head.v_template[:, 0] > 0)
    )
    right = np.flatnonzero(
        (head.vertex_region == REGION_NAMES.index("eyes")) & (head.v_template[:, 0] < 0)
    )
    aa = [0.0, 0.4, 0.0]
    out = head.skin(pose=_pose(leye=aa))
    centre = A.JOINTS[3]
    rot = axis_angle_to_matrix(torch.tensor(aa, dtype=torch.float64)).numpy()
    want = (head.v_template[left] - centre) @ rot.T + centre
    np.testing.assert_allclose(out.verts[0, left].numpy(), want, atol=1e-6)
    np.testing.assert_allclose(out.verts[0, right].numpy(), head.v_template[right], atol=1e-7)
    # the pupil (front pole) now looks to the subject's left
    front = left[np.argmax(head.v_template[left, 2])]
    assert out.verts[0, front, 0] - centre[0] > 0.004


def _lip_gap(verts, head):
    """Height of the slit at the middle of the mouth: the upper-lip edge vertex (its faces
    lie above the mouth line) minus its lower-lip twin."""
    v = head.v_template
    pair = np.flatnonzero(
        (np.abs(v[:, 0]) < 2e-3) & (np.abs(v[:, 1] - A.MOUTH_Y) < 1e-3) & (v[:, 2] > 0.08)
    )
    assert pair.size == 2
    above = [v[head.faces[np.any(head.faces == i, axis=1)], 1].mean() > A.MOUTH_Y for i in pair]
    upper, lower = (pair[0], pair[1]) if above[0] else (pair[1], pair[0])
    assert above[0] != above[1]
    return verts[upper, 1] - verts[lower, 1]


def _teeth_rows(head):
    """The two teeth rows (connected components), upper first."""
    teeth = np.flatnonzero(head.vertex_region == REGION_NAMES.index("teeth"))
    faces = head.faces[np.all(np.isin(head.faces, teeth), axis=1)]
    graph = scipy.sparse.coo_matrix(
        (np.ones(faces.size), (faces.ravel(), np.repeat(faces[:, :1], 3, 1).ravel())),
        shape=(head.num_vertices,) * 2,
    )
    _, comp = scipy.sparse.csgraph.connected_components(graph, directed=False)
    rows = [teeth[comp[teeth] == c] for c in np.unique(comp[teeth])]
    assert len(rows) == 2
    return sorted(rows, key=lambda ids: -head.v_template[ids, 1].mean())


def test_lips_part_when_the_jaw_opens(head):
    rest = _lip_gap(head.v_template.astype(np.float64), head)
    assert rest == 0  # closed at rest: the two edges of the slit coincide
    opened = head.skin(pose=_pose(jaw=[0.3, 0, 0])).verts[0].numpy()
    assert _lip_gap(opened, head) > 0.012
    # lower teeth go with the jaw, upper teeth stay
    upper, lower = _teeth_rows(head)
    np.testing.assert_allclose(opened[upper], head.v_template[upper], atol=1e-7)
    assert opened[lower, 1].mean() < head.v_template[lower, 1].mean() - 0.01


def test_blink_closes_the_lids_over_the_eyeballs(head):
    eye = A.JOINTS[3]
    skin = np.isin(head.vertex_region, [0, 1, 2, 5])
    near = skin & (np.linalg.norm(head.v_template - eye, axis=1) < A.EYE_RADIUS + 4e-3)
    near &= head.v_template[:, 2] > eye[2]
    dist_rest = np.linalg.norm(head.v_template[near] - eye, axis=1)
    assert dist_rest.min() < A.EYE_RADIUS  # open: some lid skin is tucked behind the eyeball
    closed = head.skin(expr=_expr("blink")).verts[0].numpy()
    assert np.linalg.norm(closed[near] - eye, axis=1).min() > A.EYE_RADIUS + 0.0005


@pytest.mark.parametrize("name", ["smile", "brow_raise", "pucker", "cheek_puff"])
def test_expressions_are_smooth_local_and_sized(head, name):
    d = head.shapedirs[:, :, NUM_SHAPE + EXPRESSION_NAMES.index(name)].astype(np.float64)
    mag = np.linalg.norm(d, axis=1)
    assert 0.003 < mag.max() < 0.02  # a few millimetres
    assert np.all(mag[head.vertex_region == REGION_NAMES.index("eyes")] == 0)
    assert np.all(mag[head.vertex_region == REGION_NAMES.index("teeth")] == 0)
    # smooth: neighbours along edges move alike
    edges = np.concatenate([head.faces[:, [0, 1]], head.faces[:, [1, 2]], head.faces[:, [2, 0]]])
    jump = np.linalg.norm(d[edges[:, 0]] - d[edges[:, 1]], axis=1)
    assert jump.max() < 0.5 * mag.max()


def test_skinning_is_well_formed_at_extreme_poses_and_expressions(head):
    rng = np.random.default_rng(7)
    B = 6
    pose = torch.tensor(rng.uniform(-1, 1, (B, 15)) * np.pi / 2)
    pose[:, 6] = torch.linspace(-0.2, 0.7, B, dtype=torch.float64)  # jaw from closed to wide
    pose[:, 9:] = torch.tensor(rng.uniform(-0.6, 0.6, (B, 6)))
    shape = torch.tensor(rng.uniform(-3, 3, (B, NUM_SHAPE)))
    expr = torch.tensor(rng.uniform(-3, 3, (B, NUM_EXPR)))
    out = head.skin(shape, expr, pose, torch.tensor(rng.normal(0, 0.1, (B, 3))))
    verts = out.verts.numpy()
    assert np.all(np.isfinite(verts)) and np.all(np.isfinite(out.rotations.numpy()))
    rest_area = _face_areas(head.v_template.astype(np.float64), head.faces)
    assert rest_area.min() > 1e-10  # no degenerate face at rest
    for b in range(B):
        area = _face_areas(verts[b], head.faces)
        degenerate = int((area < 1e-10).sum())
        # counted and bounded: extreme random coefficients may crush a few slivers
        assert degenerate <= 0.002 * head.num_faces, degenerate
        stretch = area / rest_area
        assert np.median(stretch) == pytest.approx(1.0, abs=0.35)
