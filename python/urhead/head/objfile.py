"""Reading the geometry and UV layout of a Wavefront OBJ (FLAME's head_template_mesh.obj:
5023 ``v``, 5118 ``vt``, 9976 ``f v/vt``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from urhead.errors import IndexRangeError, InvalidArgumentError


@dataclass(frozen=True)
class ObjMesh:
    vertices: np.ndarray
    """(V, 3) float64 positions."""
    uv_coords: np.ndarray
    """(T, 2) float64 ``vt`` coordinates."""
    faces: np.ndarray
    """(F, 3) int64 vertex indices (0-based); polygons are fan-triangulated."""
    uv_faces: np.ndarray
    """(F, 3) int64 ``vt`` indices, or (0, 3) when the faces carry none."""


def read_obj(path) -> ObjMesh:
    """Read ``v``, ``vt`` and ``f`` records (``f v``, ``f v/vt``, ``f v/vt/vn``, ``f v//vn``,
    negative indices relative to the end); everything else is ignored. Either every face
    has ``vt`` indices or none has."""
    verts, uvs, faces, uv_faces = [], [], [], []
    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            tag = parts[0]
            try:
                if tag == "v":
                    verts.append([float(x) for x in parts[1:4]])
                elif tag == "vt":
                    uvs.append([float(x) for x in parts[1:3]])
                elif tag == "f":
                    corners = [c.split("/") for c in parts[1:]]
                    if len(corners) < 3:
                        raise ValueError("a face needs at least 3 corners")
                    vi = [_index(c[0], len(verts)) for c in corners]
                    ti = [_index(c[1], len(uvs)) if len(c) > 1 and c[1] else None for c in corners]
                    for k in range(1, len(corners) - 1):  # fan triangulation
                        faces.append([vi[0], vi[k], vi[k + 1]])
                        uv_faces.append([ti[0], ti[k], ti[k + 1]])
            except (ValueError, IndexError) as e:
                raise InvalidArgumentError(f"{path}:{lineno}: bad {tag!r} record: {e}") from e
    vertices = np.asarray(verts, np.float64).reshape(-1, 3)
    uv_coords = np.asarray(uvs, np.float64).reshape(-1, 2)
    faces_a = np.asarray(faces, np.int64).reshape(-1, 3)
    has_uv = [all(t is not None for t in row) for row in uv_faces]
    if any(has_uv) and not all(has_uv):
        raise InvalidArgumentError(f"{path}: some faces have vt indices and some do not")
    uv_faces_a = np.asarray(uv_faces if all(has_uv) and has_uv else [], np.int64).reshape(-1, 3)
    for name, idx, n in (("f", faces_a, len(vertices)), ("f vt", uv_faces_a, len(uv_coords))):
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise IndexRangeError(f"{path}: {name} indices must be in [1, {n}]")
    return ObjMesh(vertices, uv_coords, faces_a, uv_faces_a)


def _index(token: str, count: int) -> int:
    i = int(token)
    if i == 0:
        raise ValueError("OBJ indices start at 1")
    return i - 1 if i > 0 else count + i
