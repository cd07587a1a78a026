"""Loop subdivision as a sparse matrix: built once from the topology, applied to every
frame's skinned vertices (and to any per-vertex attribute) with one sparse product."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def loop_subdivision(faces: np.ndarray, num_verts: int):
    """One level of Loop subdivision.

    Returns ``(S, new_faces, parent)``: ``S`` (V + E, V) CSR so that ``S @ verts`` gives
    the subdivided vertices (old vertices first, then one per edge), ``new_faces`` (4F, 3)
    with the orientation of ``faces``, ``parent`` (4F,) the coarse face of each new face.
    Boundary and non-manifold edges are creases (midpoints, and the 3/4–1/8 rule for
    vertices on exactly two of them; other crease vertices stay put), so open rims, the
    lip slit and separate parts keep their outlines.
    """
    faces = np.asarray(faces, np.int64)
    F = len(faces)
    corner_a = faces.reshape(-1)
    corner_b = np.roll(faces, -1, axis=1).reshape(-1)
    opposite = np.roll(faces, -2, axis=1).reshape(-1)
    lo, hi = np.minimum(corner_a, corner_b), np.maximum(corner_a, corner_b)
    edges, edge_of = np.unique(np.stack([lo, hi], 1), axis=0, return_inverse=True)
    edge_of = edge_of.reshape(-1)
    E = len(edges)
    count = np.bincount(edge_of, minlength=E)
    interior = count == 2

    rows, cols, vals = [], [], []

    def add(r, c, v):
        rows.append(np.asarray(r))
        cols.append(np.asarray(c))
        vals.append(np.broadcast_to(np.asarray(v, np.float64), np.shape(r)))

    # Edge points.
    e_ids = np.arange(E)
    w_end = np.where(interior, 3 / 8, 1 / 2)
    add(num_verts + e_ids, edges[:, 0], w_end)
    add(num_verts + e_ids, edges[:, 1], w_end)
    face_edge_interior = interior[edge_of]
    add(num_verts + edge_of[face_edge_interior], opposite[face_edge_interior], 1 / 8)

    # Vertex points.
    crease = ~interior
    neighbours = np.concatenate([edges, edges[:, ::-1]])  # (2E, 2): (vertex, neighbour)
    is_crease = np.concatenate([crease, crease])
    valence = np.bincount(neighbours[:, 0], minlength=num_verts)
    crease_count = np.bincount(neighbours[is_crease, 0], minlength=num_verts)
    smooth_vertex = crease_count == 0
    n = np.maximum(valence, 1)
    beta = np.where(n > 3, 3 / (8 * n), 3 / 16)
    keep_smooth = smooth_vertex & (valence > 0)
    v_ids = np.arange(num_verts)
    self_w = np.where(keep_smooth, 1 - n * beta, np.where(crease_count == 2, 3 / 4, 1.0))
    add(v_ids, v_ids, self_w)
    from_smooth = keep_smooth[neighbours[:, 0]]
    add(
        neighbours[from_smooth, 0],
        neighbours[from_smooth, 1],
        beta[neighbours[from_smooth, 0]],
    )
    along = is_crease & (crease_count[neighbours[:, 0]] == 2)
    add(neighbours[along, 0], neighbours[along, 1], 1 / 8)

    S = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(num_verts + E, num_verts),
    )
    mid = num_verts + edge_of.reshape(F, 3)  # midpoints of edges (a,b), (b,c), (c,a)
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate(
        [np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))]
    )
    parent = np.tile(np.arange(F), 4)
    return S, new_faces.astype(np.int32), parent


def subdivide(faces: np.ndarray, num_verts: int, levels: int):
    """``levels`` Loop levels composed: ``(S, faces, parent)`` as in
    :func:`loop_subdivision`, ``S`` mapping the original vertices directly."""
    S = sp.identity(num_verts, format="csr")
    parent = np.arange(len(faces))
    faces = np.asarray(faces, np.int64)
    for _ in range(levels):
        step, faces, level_parent = loop_subdivision(faces, S.shape[0])
        S = (step @ S).tocsr()
        parent = parent[level_parent]
    return S, np.asarray(faces, np.int32), parent
