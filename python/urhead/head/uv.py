"""UV-space tools: the seam-free per-vertex UV, locating UV points on the mesh, and region
masks as images.

Conventions (DESIGN.md): OBJ ``vt`` UVs, u to the right, v up; texel row 0 is v = 1, so
texel (row r, column c) of an H×W map has its centre at u = (c + 0.5)/W,
v = 1 − (r + 0.5)/H.
"""

from __future__ import annotations

import numpy as np

from urhead.errors import IndexRangeError, InvalidArgumentError, ShapeError
from urhead.head.model import REGION_NAMES, HeadModel


def seam_free_vertex_uv(
    faces: np.ndarray, uv_faces: np.ndarray, uv_coords: np.ndarray, num_vertices: int
) -> np.ndarray:
    """(V, 2) float32: each vertex takes the UV of its first occurrence in ``faces``
    (row-major: face 0 corners 0, 1, 2, then face 1, …), the seam-free map of the URHead
    supplement. A vertex on a UV seam has several UVs; this picks one, so per-vertex
    attributes sampled from UV maps are single-valued.

    Args:
        faces: (F, 3) vertex indices. uv_faces: (F, 3) indices into ``uv_coords`` (T, 2).

    Raises :class:`~urhead.errors.InvalidArgumentError` if a vertex is used by no face.
    """
    faces = np.asarray(faces)
    uv_faces = np.asarray(uv_faces)
    if faces.shape != uv_faces.shape or faces.ndim != 2 or faces.shape[1] != 3:
        raise ShapeError(
            f"faces and uv_faces must both be (F, 3), got {faces.shape} and {uv_faces.shape}"
        )
    flat_v = faces.reshape(-1)
    if flat_v.size and (flat_v.min() < 0 or flat_v.max() >= num_vertices):
        raise IndexRangeError(f"faces must index [0, {num_vertices})")
    # np.unique returns the first index of each value in the flattened order.
    used, first = np.unique(flat_v, return_index=True)
    if used.size != num_vertices:
        unused = np.setdiff1d(np.arange(num_vertices), used)
        raise InvalidArgumentError(
            f"{unused.size} vertices are used by no face (first: {unused[:5].tolist()}); "
            "they have no UV"
        )
    return np.asarray(uv_coords, np.float32)[uv_faces.reshape(-1)[first]]


def texel_centers(resolution) -> np.ndarray:
    """(H·W, 2) float64 UVs of the texel centres of an H×W map, row-major from row 0
    (v near 1). ``resolution`` is an int (square) or (H, W)."""
    h, w = _resolution(resolution)
    u = (np.arange(w) + 0.5) / w
    v = 1.0 - (np.arange(h) + 0.5) / h
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], 1)


class UvLookup:
    """Finds, for any UV point, the UV triangle containing it and its barycentrics.

    Triangles are bucketed by their UV bounding boxes on a ``grid × grid`` cell grid
    (CSR lists); a query tests only the triangles of its cell, exactly, in float64. Where
    triangles overlap in UV (a layout fault), the lowest face index wins; points on a shared
    edge likewise resolve to the lower index. Points in no triangle, outside [0, 1]² or
    non-finite get face −1 and barycentrics 0.

    Args:
        uv_coords: (T, 2) UVs. uv_faces: (F, 3) indices into ``uv_coords``.
        grid: cells per side; ~sqrt(F) keeps a few triangles per cell.
    """

    def __init__(self, uv_coords: np.ndarray, uv_faces: np.ndarray, grid: int | None = None):
        uv_coords = np.asarray(uv_coords, np.float64)
        uv_faces = np.asarray(uv_faces, np.int64)
        if uv_coords.ndim != 2 or uv_coords.shape[1] != 2:
            raise ShapeError(f"uv_coords must be (T, 2), got {uv_coords.shape}")
        if uv_faces.ndim != 2 or uv_faces.shape[1] != 3 or uv_faces.shape[0] == 0:
            raise ShapeError(f"uv_faces must be (F, 3) with F > 0, got {uv_faces.shape}")
        if uv_faces.min() < 0 or uv_faces.max() >= uv_coords.shape[0]:
            raise IndexRangeError(f"uv_faces must index uv_coords [0, {uv_coords.shape[0]})")
        if grid is None:
            grid = int(np.clip(np.sqrt(uv_faces.shape[0]), 8, 1024))
        self.grid = int(grid)
        self.corners = uv_coords[uv_faces]  # (F, 3, 2)
        lo = np.floor(self.corners.min(1) * self.grid).astype(np.int64)
        hi = np.floor(self.corners.max(1) * self.grid).astype(np.int64)
        lo = np.clip(lo, 0, self.grid - 1)
        hi = np.clip(hi, 0, self.grid - 1)
        nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
        counts = nx * ny
        tri = np.repeat(np.arange(len(counts)), counts)
        local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        cx = lo[tri, 0] + local % nx[tri]
        cy = lo[tri, 1] + local // nx[tri]
        cell = cy * self.grid + cx
        order = np.lexsort((tri, cell))  # by cell, then face index (lowest wins)
        self.cell_faces = tri[order]
        self.cell_start = np.searchsorted(cell[order], np.arange(self.grid * self.grid + 1))

    def locate(self, uv: np.ndarray, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
        """``uv`` (N, 2) → ``(face (N,) int64, bary (N, 3) float64)``; barycentrics weight
        the UV corners ``uv_faces[face]`` and sum to 1 (clamped to the simplex)."""
        uv = np.asarray(uv, np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ShapeError(f"uv must be (N, 2), got {uv.shape}")
        face = np.full(len(uv), -1, np.int64)
        bary = np.zeros((len(uv), 3))
        for s in range(0, len(uv), chunk):
            face[s : s + chunk], bary[s : s + chunk] = self._locate_chunk(uv[s : s + chunk])
        return face, bary

    def _locate_chunk(self, uv):
        n = len(uv)
        face = np.full(n, -1, np.int64)
        bary = np.zeros((n, 3))
        ok = np.all(np.isfinite(uv), 1) & np.all((uv >= 0) & (uv <= 1), 1)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return face, bary
        c = np.minimum((uv[idx] * self.grid).astype(np.int64), self.grid - 1)
        cell = c[:, 1] * self.grid + c[:, 0]
        start, count = self.cell_start[cell], self.cell_start[cell + 1] - self.cell_start[cell]
        width = int(count.max()) if count.size else 0
        if width == 0:
            return face, bary
        slot = np.arange(width)
        valid = slot[None] < count[:, None]
        cand = self.cell_faces[np.where(valid, start[:, None] + slot[None], 0)]  # (n, K)
        b = _barycentrics(self.corners[cand], uv[idx][:, None, :])  # (n, K, 3)
        inside = valid & np.all(b >= -1e-9, -1)
        hit = inside.any(1)
        first = np.argmax(inside, 1)
        rows = idx[hit]
        face[rows] = cand[hit, first[hit]]
        chosen = np.clip(b[hit, first[hit]], 0.0, None)
        bary[rows] = chosen / chosen.sum(1, keepdims=True)
        return face, bary


def triangle_id_map(head: HeadModel, resolution) -> np.ndarray:
    """(H, W) int32: the face whose UV triangle covers each texel centre, −1 where none."""
    _require_uv(head)
    h, w = _resolution(resolution)
    face, _ = UvLookup(head.uv_coords, head.uv_faces).locate(texel_centers((h, w)))
    return face.reshape(h, w).astype(np.int32)


def uv_region_masks(head: HeadModel, resolution, regions=None) -> dict[str, np.ndarray]:
    """(H, W) bool images of where each region lies in UV: a texel belongs to the region of
    the face covering its centre (:meth:`HeadModel.face_region`). ``regions`` defaults to
    all of :data:`REGION_NAMES` (face, scalp, neck, ears, eyes, lips, mouth_interior,
    teeth)."""
    regions = REGION_NAMES if regions is None else tuple(regions)
    for name in regions:
        if name not in REGION_NAMES:
            raise InvalidArgumentError(f"regions must be among {REGION_NAMES}, got {name!r}")
    ids = triangle_id_map(head, resolution)
    labels = np.where(ids >= 0, head.face_region()[np.maximum(ids, 0)], -1)
    return {name: labels == REGION_NAMES.index(name) for name in regions}


def _barycentrics(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """tri (..., 3, 2), p (..., 2) → (..., 3); degenerate triangles give NaN (never inside)."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        l1 = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
        l2 = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    l1 = np.where(den != 0, l1, np.nan)
    return np.stack([1 - l1 - l2, l1, l2], -1)


def _resolution(resolution) -> tuple[int, int]:
    h, w = (resolution, resolution) if np.isscalar(resolution) else tuple(resolution)
    if int(h) != h or int(w) != w or h < 1 or w < 1:
        raise InvalidArgumentError(f"resolution must be positive ints, got {resolution!r}")
    return int(h), int(w)


def _require_uv(head: HeadModel) -> None:
    if not head.has_uv:
        raise InvalidArgumentError(
            "this head model has no UV layout; convert FLAME with its head_template_mesh.obj "
            "(urhead convert-flame PKL --obj OBJ)"
        )
