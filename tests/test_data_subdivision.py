"""Loop subdivision, the surface the synthetic subjects are ray-traced from: Loop's own
weights on a closed mesh, and boundary edges kept as creases (open rims, the lip slit)."""

from __future__ import annotations

import numpy as np
import pytest

from urhead.data.synth.subdivision import loop_subdivision, subdivide

OCTAHEDRON = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
)
OCTAHEDRON_VERTS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64
)


def test_loop_weights_on_a_closed_mesh():
    S, faces, parent = loop_subdivision(OCTAHEDRON, 6)
    assert S.shape == (6 + 12, 6) and faces.shape == (32, 3)
    np.testing.assert_array_equal(np.bincount(parent), [4] * 8)
    dense = S.toarray()
    # Valence 4: the vertex keeps 1 − 4·3/32 = 5/8 and takes 3/32 of each neighbour.
    assert dense[0, 0] == pytest.approx(5 / 8)
    assert dense[0, [2, 3, 4, 5]] == pytest.approx([3 / 32] * 4)
    assert dense[0, 1] == 0
    # An interior edge point: 3/8 of its ends, 1/8 of the two opposite vertices.
    edge_rows = dense[6:]
    assert sorted(np.round(edge_rows[0][edge_rows[0] > 0] * 8).tolist()) == [1, 1, 3, 3]
    np.testing.assert_allclose(dense.sum(1), 1)
    # A sphere-like surface shrinks toward its centre; its symmetry is kept.
    out = S @ OCTAHEDRON_VERTS
    radii = np.linalg.norm(out, axis=1)
    np.testing.assert_allclose(radii[:6], radii[0])
    assert radii.max() < 1


def test_boundary_edges_are_creases():
    # Two triangles sharing one edge: the four outer edges are a boundary.
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0]], np.float64)
    S, _, _ = loop_subdivision(faces, 4)
    out = S @ verts
    # A boundary edge's point is its midpoint; a boundary vertex on two boundary edges
    # keeps 3/4 and takes 1/8 of each boundary neighbour (the outline stays an outline).
    edges = {tuple(sorted(e)) for f in faces for e in zip(f, np.roll(f, -1), strict=True)}
    assert len(edges) == 5
    np.testing.assert_allclose(out[1], 0.75 * verts[1] + 0.125 * (verts[0] + verts[2]))
    mids = out[4:]
    boundary_mids = [0.5 * (verts[a] + verts[b]) for a, b in [(0, 1), (1, 2), (2, 3), (0, 3)]]
    for m in boundary_mids:
        assert np.min(np.linalg.norm(mids - m, axis=1)) < 1e-12


def test_levels_compose():
    S1, faces1, _ = loop_subdivision(OCTAHEDRON, 6)
    S2, _, _ = loop_subdivision(faces1, S1.shape[0])
    S, faces, parent = subdivide(OCTAHEDRON, 6, 2)
    np.testing.assert_allclose(S.toarray(), (S2 @ S1).toarray())
    assert faces.shape == (8 * 16, 3)
    np.testing.assert_array_equal(np.bincount(parent), [16] * 8)
