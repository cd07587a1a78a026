"""Operators on a triangle mesh: its Laplacian and its vertex normals (torch for the model,
numpy for synthesis and the ray tracer)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch


def uniform_laplacian(faces: torch.Tensor, num_verts: int) -> sp.csr_matrix:
    """Sparse (V, V) float32 operator L with (L v)_i = v_i − mean of i's edge neighbours
    (a scipy CSR matrix: :func:`urhead.train.objective.laplacian_loss` applies it and its
    transpose in one pass each). Isolated vertices get a zero row."""
    f = faces.long()
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges = torch.cat([edges, edges.flip(1)]).unique(dim=0)
    degree = torch.bincount(edges[:, 0], minlength=num_verts).to(torch.float32)
    rows = torch.cat([edges[:, 0], torch.arange(num_verts)])
    cols = torch.cat([edges[:, 1], torch.arange(num_verts)])
    has_neighbours = (degree > 0).to(torch.float32)
    values = torch.cat([-1 / degree[edges[:, 0]], has_neighbours])
    shape = (num_verts, num_verts)
    return sp.csr_matrix((values.numpy(), (rows.numpy(), cols.numpy())), shape=shape)


def vertex_normals(verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(V, 3) area-weighted unit vertex normals of counter-clockwise faces."""
    f = faces.long()
    a, b, c = verts[f[:, 0]], verts[f[:, 1]], verts[f[:, 2]]
    face_n = torch.linalg.cross(b - a, c - a)
    n = torch.zeros_like(verts).index_add_(0, f.reshape(-1), face_n.repeat_interleave(3, 0))
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def vertex_normal_operator(faces: np.ndarray, num_verts: int) -> sp.csr_matrix:
    """(V, F) incidence matrix: ``A @ face_cross_products`` sums each vertex's
    area-weighted face normals (normalise afterwards)."""
    F = len(faces)
    rows = np.asarray(faces, np.int64).reshape(-1)
    cols = np.repeat(np.arange(F), 3)
    return sp.csr_matrix((np.ones(3 * F), (rows, cols)), shape=(num_verts, F))


def vertex_normals_numpy(
    verts: np.ndarray, faces: np.ndarray, operator: sp.csr_matrix | None = None
) -> np.ndarray:
    """(V, 3) float32 unit area-weighted vertex normals of (V, 3) ``verts`` and (F, 3)
    counter-clockwise ``faces``, through ``operator`` (:func:`vertex_normal_operator`,
    built here when not given; pass it when the topology is reused); zero for unused
    vertices."""
    if operator is None:
        operator = vertex_normal_operator(faces, len(verts))
    # Per-column gathers and products into preallocated columns: ~1.5× faster than
    # ``np.cross`` on gathered (F, 3, 3) corners, same values.
    a = verts[faces[:, 0]]
    e1 = verts[faces[:, 1]] - a
    e2 = verts[faces[:, 2]] - a
    cross = np.empty_like(e1)
    for k, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(e1[:, i], e2[:, j], out=cross[:, k])
        cross[:, k] -= e1[:, j] * e2[:, i]
    n = operator @ cross
    n /= np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), 1e-20)[:, None]
    return n.astype(np.float32)
