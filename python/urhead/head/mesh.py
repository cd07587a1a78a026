"""Operators on a triangle mesh's connectivity."""

from __future__ import annotations

import torch


def uniform_laplacian(faces: torch.Tensor, num_verts: int) -> torch.Tensor:
    """Sparse (V, V) operator L with (L v)_i = v_i − mean of i's edge neighbours.
    Isolated vertices get a zero row."""
    f = faces.long()
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges = torch.cat([edges, edges.flip(1)]).unique(dim=0)
    degree = torch.bincount(edges[:, 0], minlength=num_verts).to(torch.float32)
    rows = torch.cat([edges[:, 0], torch.arange(num_verts)])
    cols = torch.cat([edges[:, 1], torch.arange(num_verts)])
    has_neighbours = (degree > 0).to(torch.float32)
    values = torch.cat([-1 / degree[edges[:, 0]], has_neighbours])
    return torch.sparse_coo_tensor(
        torch.stack([rows, cols]), values, (num_verts, num_verts), check_invariants=True
    ).coalesce()
