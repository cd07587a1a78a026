"""A head without some of its regions (the mouth interior and teeth of a subject who never
opens the mouth): their faces are gone, and so is the band of UV-atlas rows only they
used, so a fit allocates, steps and saves no texel for them.

The atlas of a kept head is a window of rows ``[first_row, first_row + height)`` of the
full ``R × R`` atlas: its UVs are rescaled in v so that its texel ``(r, c)`` has the centre
of the full atlas's texel ``(first_row + r, c)``. Every texel a kept face samples therefore
holds what it would hold in the full atlas; maps of such a head are ``(height, R)``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np

from urhead.errors import InvalidArgumentError
from urhead.head.model import REGION_NAMES, HeadModel, region_index

BILINEAR_MARGIN = 1
"""Rows kept on each side of the kept faces' UV extent: a bilinear lookup near a
triangle's edge reads the neighbouring texel row."""


class KeptHead(NamedTuple):
    head: HeadModel
    """The head without the left-out regions' faces, UVs rescaled to the row window."""
    first_row: int
    """The window's first row in the full atlas."""
    map_size: tuple[int, int]
    """``(height, width)`` of the maps of ``head``; width is the full atlas side."""
    faces_left_out: int
    """Faces removed."""


def region_faces(head: HeadModel, regions: tuple[str, ...]) -> np.ndarray:
    """(F,) bool: the faces of ``regions`` (names of :data:`REGION_NAMES`)."""
    for name in regions:
        if name not in REGION_NAMES:
            raise InvalidArgumentError(f"regions must be among {REGION_NAMES}, got {name!r}")
    return np.isin(head.face_region(), [region_index(name) for name in regions])


def leave_out_faces(head: HeadModel, dropped: np.ndarray, resolution: int) -> KeptHead:
    """``head`` without the faces ``dropped`` ((F,) bool) and with the atlas rows of an
    ``resolution``² map that no kept face reaches left out.

    Vertices are all kept (skinning, the joint regressor and VHAP's ``static_offset`` stay
    valid); a vertex no kept face uses is never drawn and reads the window's nearest texel.
    A kept vertex whose first face was left out takes its UV from its first kept face."""
    dropped = np.asarray(dropped, bool)
    if not head.has_uv:
        raise InvalidArgumentError("the head model has no UV layout; faces cannot be left out")
    if dropped.shape != (head.num_faces,):
        raise InvalidArgumentError(
            f"dropped must be one flag per face ({head.num_faces}), got {dropped.shape}"
        )
    if dropped.all():
        raise InvalidArgumentError("leaving out every face would leave no head")
    faces = head.faces[~dropped]
    uv_faces = head.uv_faces[~dropped]
    used_uv = np.unique(uv_faces)
    v = head.uv_coords[used_uv, 1].astype(np.float64)
    # Texel rows (row 0 at v = 1) the kept faces cover, widened by the bilinear margin.
    top = int(np.floor((1.0 - v.max()) * resolution)) - BILINEAR_MARGIN
    bottom = int(np.ceil((1.0 - v.min()) * resolution)) + BILINEAR_MARGIN
    first_row, last_row = max(top, 0), min(bottom, resolution)
    height = last_row - first_row
    # v in the window: the full atlas's v of its rows [first_row, last_row) spans
    # [1 − last_row/R, 1 − first_row/R].
    v_low, span = 1.0 - last_row / resolution, height / resolution

    def window(uv: np.ndarray) -> np.ndarray:
        out = np.asarray(uv, np.float64).copy()
        out[:, 1] = np.clip((out[:, 1] - v_low) / span, 0.0, 1.0)
        return out.astype(np.float32)

    uv_remap = np.full(head.uv_coords.shape[0], -1, np.int64)
    uv_remap[used_uv] = np.arange(used_uv.size)
    vertex_uv = head.vertex_uv.copy()
    # Each used vertex's UV from its first occurrence among the kept faces (seam-free).
    used_vertices, first = np.unique(faces.reshape(-1), return_index=True)
    vertex_uv[used_vertices] = head.uv_coords[uv_faces.reshape(-1)[first]]
    kept = replace(
        head,
        faces=faces,
        uv_faces=uv_remap[uv_faces].astype(np.int32),
        uv_coords=window(head.uv_coords[used_uv]),
        vertex_uv=window(vertex_uv),
    )
    return KeptHead(kept, first_row, (height, resolution), int(dropped.sum()))
