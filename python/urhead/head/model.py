"""The head model every part of urhead reads: a FLAME-structured mesh with blendshapes,
skinning and a UV layout, and its ``.npz`` file format.

A :class:`HeadModel` comes from :func:`urhead.head.load_flame` (the official, licensed
FLAME files, converted once), from :func:`urhead.head.procedural_head` (the built-in
head) or from :func:`load_head` (our ``.npz``). Everything downstream reads only this.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from urhead._atomic import write_file_atomically
from urhead.errors import (
    DTypeError,
    IndexRangeError,
    InvalidArgumentError,
    ShapeError,
    reading,
)

FORMAT_VERSION = 1
"""Version of the ``.npz`` head format written by :func:`save_head`."""

REGION_NAMES = (
    "face",
    "scalp",
    "neck",
    "ears",
    "eyes",
    "lips",
    "mouth_interior",
    "teeth",
)
"""Per-vertex region labels index this tuple: ``vertex_region[i] == 4`` means an eyeball
vertex. ``scalp`` is where hair grows; ``mouth_interior`` is the inner lips, mouth bag and
mouth plate; ``teeth`` the two teeth rows."""

JOINT_NAMES = ("root", "neck", "jaw", "left_eye", "right_eye")
"""FLAME's joints; pose vectors are (global, neck, jaw, left eye, right eye) axis-angles."""


@dataclass(frozen=True, eq=False)
class LbsTables:
    """The constant tensors :func:`urhead.ops.lbs` takes, named as its keyword arguments
    (``lbs(betas, pose, **tables)`` unpacks them)."""

    v_template: torch.Tensor
    """(V, 3) rest vertices."""
    shapedirs: torch.Tensor
    """(V, 3, NB) identity then expression blendshapes."""
    posedirs: torch.Tensor
    """(9·(J−1), V·3) pose correctives."""
    j_regressor: torch.Tensor
    """(J, V) joint regressor."""
    parents: torch.Tensor
    """(J,) int32 parent joint, −1 for the root."""
    lbs_weights: torch.Tensor
    """(V, J) skinning weights."""

    def keys(self) -> list[str]:
        return [f.name for f in fields(self)]

    def __getitem__(self, name: str) -> torch.Tensor:
        return getattr(self, name)


@dataclass(frozen=True, eq=False)
class HeadModel:
    """A FLAME-structured head: template, blendshapes, skinning and UV layout.

    Arrays (float32 unless stated; ``V`` vertices, ``F`` faces, ``J`` joints, ``T`` UV
    coordinates, ``NB = num_shape + num_expr``):

    - ``v_template`` (V, 3) rest vertices in metres; y up, z out of the face, +x the
      subject's left (FLAME's frame).
    - ``faces`` (F, 3) int32, counter-clockwise seen from outside.
    - ``shapedirs`` (V, 3, NB): identity columns first, then expression (FLAME layout).
    - ``posedirs`` (9·(J−1), V·3) against the flattened (R_j − I) of the non-root joints.
    - ``j_regressor`` (J, V), dense.
    - ``parents`` (J,) int32, ``parents[0] == -1``.
    - ``lbs_weights`` (V, J), non-negative, rows sum to 1.
    - ``uv_coords`` (T, 2) in [0, 1], OBJ ``vt`` convention (u right, v up).
    - ``uv_faces`` (F, 3) int32 into ``uv_coords``, one row per face.
    - ``vertex_uv`` (V, 2): the seam-free per-vertex UV (each vertex takes the UV of its
      first occurrence in ``faces``; see :func:`urhead.head.uv.seam_free_vertex_uv`).
    - ``vertex_region`` (V,) int32 into :data:`REGION_NAMES`.

    A model may have no UV layout (FLAME converted without its OBJ): then ``uv_coords``,
    ``uv_faces`` and ``vertex_uv`` have zero rows, :attr:`has_uv` is False and UV
    operations raise :class:`~urhead.errors.InvalidArgumentError`.

    Arrays are validated on construction and made read-only. Build one with plain numpy
    arrays; dtypes are converted (float64 → float32, int64 → int32) when lossless.
    """

    v_template: np.ndarray
    faces: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    j_regressor: np.ndarray
    parents: np.ndarray
    lbs_weights: np.ndarray
    uv_coords: np.ndarray
    uv_faces: np.ndarray
    vertex_uv: np.ndarray
    vertex_region: np.ndarray
    num_shape: int
    num_expr: int

    def __post_init__(self):
        for name in _FLOAT_KEYS:
            object.__setattr__(self, name, _as_float32(name, getattr(self, name)))
        for name in _INT_KEYS:
            object.__setattr__(self, name, _as_int32(name, getattr(self, name)))
        for name in ("num_shape", "num_expr"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise InvalidArgumentError(f"{name} must be a non-negative int, got {value!r}")
            object.__setattr__(self, name, int(value))
        _validate(self)
        for name in (*_FLOAT_KEYS, *_INT_KEYS):
            getattr(self, name).setflags(write=False)

    @property
    def num_vertices(self) -> int:
        return self.v_template.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]

    @property
    def num_joints(self) -> int:
        return self.parents.shape[0]

    @property
    def has_uv(self) -> bool:
        return self.uv_faces.shape[0] > 0

    def region_vertices(self, name: str) -> np.ndarray:
        """(K,) int64 indices of the vertices labelled ``name`` (one of REGION_NAMES)."""
        return np.flatnonzero(self.vertex_region == region_index(name))

    def face_region(self) -> np.ndarray:
        """(F,) int32 region of each face: the label most of its vertices share, else the
        label of its first vertex."""
        labels = self.vertex_region[self.faces]
        first, second, third = labels[:, 0], labels[:, 1], labels[:, 2]
        return np.where((second == third) & (second != first), second, first).astype(np.int32)

    def lbs_tables(
        self, dtype: torch.dtype = torch.float32, num_shape=None, num_expr=None
    ) -> LbsTables:
        """The constant tensors :func:`urhead.ops.lbs` takes, in ``dtype``, with the first
        ``num_shape`` identity and ``num_expr`` expression columns (all by default).

        Returns :class:`LbsTables`; build them once and reuse them across iterations.
        """
        ns = self.num_shape if num_shape is None else int(num_shape)
        ne = self.num_expr if num_expr is None else int(num_expr)
        if not (0 <= ns <= self.num_shape and 0 <= ne <= self.num_expr):
            raise InvalidArgumentError(
                f"num_shape/num_expr must be within ({self.num_shape}, {self.num_expr}), "
                f"got ({ns}, {ne})"
            )
        columns = np.r_[np.arange(ns), self.num_shape + np.arange(ne)]
        shapedirs = self.shapedirs[:, :, columns]

        def tensor(a):
            return torch.tensor(
                np.ascontiguousarray(a), dtype=dtype
            )  # a copy: arrays are read-only

        return LbsTables(
            v_template=tensor(self.v_template),
            shapedirs=tensor(shapedirs),
            posedirs=tensor(self.posedirs),
            j_regressor=tensor(self.j_regressor),
            parents=torch.tensor(self.parents),
            lbs_weights=tensor(self.lbs_weights),
        )

    def skin(self, shape=None, expr=None, pose=None, transl=None):
        """Pose the head with :func:`urhead.ops.lbs` (differentiable in its inputs).

        Args:
            shape: (B, S) or (S,) identity coefficients, S ≤ num_shape; None = zeros.
            expr: (B, E) or (E,) expression coefficients, E ≤ num_expr; None = zeros.
            pose: (B, 3·J) or (3·J,) axis-angles (global, neck, jaw, left eye, right eye);
                None = zeros.
            transl: (B, 3) or (3,) translation added after skinning; None = none.

        The dtype (float32 or float64) is that of the first tensor given, float32 if none.
        Returns :class:`urhead.ops.LbsOutput` ``(verts (B, V, 3), joints (B, J, 3),
        rotations (B, V, 3, 3))``. Rebuilds the constant tables each call; loops should
        call :meth:`lbs_tables` once and :func:`urhead.ops.lbs` directly.
        """
        from urhead.ops import lbs

        given = [t for t in (shape, expr, pose, transl) if t is not None]
        for t in given:
            if not isinstance(t, torch.Tensor):
                raise DTypeError(f"skin inputs must be torch tensors, got {type(t).__name__}")
        dtype = given[0].dtype if given else torch.float32
        batch = _batch_size(given)

        def batched(name, t, width):
            if t is None:
                return torch.zeros(batch, width, dtype=dtype)
            t = t.reshape(1, -1) if t.dim() == 1 else t
            if t.dim() != 2 or t.shape[0] != batch:
                raise ShapeError(f"{name} must be ({batch}, K) or (K,), got {tuple(t.shape)}")
            return t.to(dtype).expand(batch, t.shape[1])

        shape = batched("shape", shape, 0)
        expr = batched("expr", expr, 0)
        pose = batched("pose", pose, 3 * self.num_joints)
        if pose.shape[1] != 3 * self.num_joints:
            raise ShapeError(f"pose must have {3 * self.num_joints} columns, got {pose.shape[1]}")
        tables = self.lbs_tables(dtype, shape.shape[1], expr.shape[1])
        betas = torch.cat([shape, expr], 1).contiguous()
        if transl is not None:
            transl = batched("transl", transl, 3).contiguous()
            if transl.shape[1] != 3:
                raise ShapeError(f"transl must have 3 columns, got {transl.shape[1]}")
        return lbs(betas, pose.contiguous(), transl=transl, **tables)


def region_index(name: str) -> int:
    """The label of region ``name`` in :data:`REGION_NAMES`."""
    if name not in REGION_NAMES:
        raise InvalidArgumentError(f"region must be one of {REGION_NAMES}, got {name!r}")
    return REGION_NAMES.index(name)


def save_head(head: HeadModel, path: str | os.PathLike) -> None:
    """Write ``head`` to ``path`` as our ``.npz`` head format (FORMATS.md): plain float32 /
    int32 arrays under the field names, ``num_shape``/``num_expr`` as int32 scalars and
    ``format_version``. Written to a temporary file in the same folder, then renamed, so a
    reader never sees a half-written file."""
    path = Path(path)
    arrays = {name: getattr(head, name) for name in (*_FLOAT_KEYS, *_INT_KEYS)}
    arrays["num_shape"] = np.int32(head.num_shape)
    arrays["num_expr"] = np.int32(head.num_expr)
    arrays["format_version"] = np.int32(FORMAT_VERSION)
    write_file_atomically(path, lambda tmp: np.savez(tmp, **arrays))


def load_head(path: str | os.PathLike, file: BinaryIO | None = None) -> HeadModel:
    """Read a head written by :func:`save_head`. ``j_regressor`` may be stored dense or as
    CSR (``j_regressor_data``, ``j_regressor_indices``, ``j_regressor_indptr``,
    ``j_regressor_shape``). Raises :class:`~urhead.errors.ShapeError` /
    :class:`~urhead.errors.InvalidArgumentError` naming the file and the bad key, a
    :class:`~urhead.errors.CorruptFileError` for a damaged file. ``file``: the file
    already open (``path`` then only names it)."""
    with reading(path, "urhead head (.npz)"):
        with np.load(Path(path) if file is None else file, allow_pickle=False) as z:
            keys = set(z.files)
            if "format_version" not in keys:
                raise InvalidArgumentError(f"{path}: not a urhead head file (no format_version)")
            version = int(z["format_version"])
            if version != FORMAT_VERSION:
                raise InvalidArgumentError(
                    f"{path}: format_version {version} is not supported (expected {FORMAT_VERSION})"
                )
            values = {}
            for name in (*_FLOAT_KEYS, *_INT_KEYS, "num_shape", "num_expr"):
                if name == "j_regressor" and name not in keys:
                    values[name] = _csr_from_file(z, keys)
                    continue
                if name not in keys:
                    raise InvalidArgumentError(f"{path}: missing key {name!r}")
                values[name] = z[name]
        for name in ("num_shape", "num_expr"):
            if values[name].shape != ():
                raise ShapeError(f"{name} must be a scalar, got shape {values[name].shape}")
            values[name] = int(values[name])
        return HeadModel(**values)


def head_fingerprint(head: HeadModel) -> str:
    """SHA-256 of every array of ``head`` (hex): recorded with an avatar and a checkpoint
    so another head is recognised."""
    digest = hashlib.sha256()
    for name in (*_FLOAT_KEYS, *_INT_KEYS):
        a = np.ascontiguousarray(getattr(head, name))
        digest.update(f"{name}{a.dtype.str}{a.shape}".encode())
        digest.update(a.tobytes())
    digest.update(f"{head.num_shape},{head.num_expr}".encode())
    return digest.hexdigest()


_FLOAT_KEYS = (
    "v_template",
    "shapedirs",
    "posedirs",
    "j_regressor",
    "lbs_weights",
    "uv_coords",
    "vertex_uv",
)
_INT_KEYS = ("faces", "parents", "uv_faces", "vertex_region")
assert {f.name for f in fields(HeadModel)} == {*_FLOAT_KEYS, *_INT_KEYS, "num_shape", "num_expr"}


def _csr_from_file(z, keys) -> np.ndarray:
    names = [f"j_regressor_{k}" for k in ("data", "indices", "indptr", "shape")]
    missing = [n for n in names if n not in keys]
    if missing:
        raise InvalidArgumentError(f"missing key 'j_regressor' (or its CSR parts {missing})")
    data, indices, indptr, shape = (z[n] for n in names)
    if shape.shape != (2,):
        raise ShapeError(f"j_regressor_shape must be (2,), got {shape.shape}")
    rows, cols = (int(s) for s in shape)
    if indptr.shape != (rows + 1,) or data.shape != indices.shape or indptr[-1] != data.size:
        raise ShapeError(
            f"j_regressor CSR parts are inconsistent: indptr {indptr.shape}, data "
            f"{data.shape}, indices {indices.shape} for shape ({rows}, {cols})"
        )
    if data.size and (indices.min() < 0 or indices.max() >= cols):
        raise IndexRangeError(f"j_regressor_indices must be in [0, {cols})")
    if indptr[0] != 0 or np.any(np.diff(indptr) < 0):
        raise InvalidArgumentError("j_regressor_indptr must start at 0 and be non-decreasing")
    dense = np.zeros((rows, cols), np.float32)
    row_of = np.repeat(np.arange(rows), np.diff(indptr))
    np.add.at(dense, (row_of, indices), data)
    return dense


def _as_float32(name: str, a) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind not in "fiu":
        raise DTypeError(f"{name} must be a float array, got dtype {a.dtype}")
    out = np.ascontiguousarray(a, dtype=np.float32)
    if not np.all(np.isfinite(out)):
        from urhead.errors import NonFiniteError

        raise NonFiniteError(f"{name} contains NaN or inf")
    return out


def _as_int32(name: str, a) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind not in "iu":
        raise DTypeError(f"{name} must be an integer array, got dtype {a.dtype}")
    if a.size and (a.min() < np.iinfo(np.int32).min or a.max() > np.iinfo(np.int32).max):
        raise IndexRangeError(f"{name} does not fit in int32")
    return np.ascontiguousarray(a, dtype=np.int32)


def _expect(name: str, a: np.ndarray, shape: tuple) -> None:
    """``shape`` entries are ints or None (any size)."""
    ok = a.ndim == len(shape) and all(
        s is None or s == d for s, d in zip(shape, a.shape, strict=True)
    )
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"{name} must be {want}, got {a.shape}")


def _validate(h: HeadModel) -> None:
    _expect("v_template", h.v_template, (None, 3))
    V = h.v_template.shape[0]
    if V == 0:
        raise ShapeError("v_template must have at least one vertex")
    _expect("parents", h.parents, (None,))
    J = h.parents.shape[0]
    if J == 0 or h.parents[0] != -1 or np.any(h.parents[1:] < 0):
        raise InvalidArgumentError(
            f"parents must start with -1 and have no other roots, got {h.parents}"
        )
    if np.any(h.parents[1:] >= np.arange(1, J)):
        raise InvalidArgumentError(f"parents[j] must be < j (topological order), got {h.parents}")
    _expect("faces", h.faces, (None, 3))
    F = h.faces.shape[0]
    if F and (h.faces.min() < 0 or h.faces.max() >= V):
        raise IndexRangeError(f"faces must index [0, {V}), got [{h.faces.min()}, {h.faces.max()}]")
    _expect("shapedirs", h.shapedirs, (V, 3, h.num_shape + h.num_expr))
    _expect("posedirs", h.posedirs, (9 * (J - 1), 3 * V))
    _expect("j_regressor", h.j_regressor, (J, V))
    _expect("lbs_weights", h.lbs_weights, (V, J))
    if h.lbs_weights.min() < 0:
        raise InvalidArgumentError("lbs_weights must be non-negative")
    worst = np.abs(h.lbs_weights.sum(1) - 1).max()
    if worst > 1e-4:
        raise InvalidArgumentError(f"lbs_weights rows must sum to 1 (worst error {worst:.2e})")
    _expect("vertex_region", h.vertex_region, (V,))
    if h.vertex_region.min() < 0 or h.vertex_region.max() >= len(REGION_NAMES):
        raise IndexRangeError(f"vertex_region must index REGION_NAMES [0, {len(REGION_NAMES)})")
    _expect("uv_coords", h.uv_coords, (None, 2))
    T = h.uv_coords.shape[0]
    if T == 0:  # no UV layout: all three UV arrays empty
        _expect("uv_faces", h.uv_faces, (0, 3))
        _expect("vertex_uv", h.vertex_uv, (0, 2))
        return
    if h.uv_coords.min() < 0 or h.uv_coords.max() > 1:
        raise InvalidArgumentError("uv_coords must lie in [0, 1]")
    _expect("uv_faces", h.uv_faces, (F, 3))
    if h.uv_faces.min() < 0 or h.uv_faces.max() >= T:
        raise IndexRangeError(f"uv_faces must index uv_coords [0, {T})")
    _expect("vertex_uv", h.vertex_uv, (V, 2))
    if h.vertex_uv.min() < 0 or h.vertex_uv.max() > 1:
        raise InvalidArgumentError("vertex_uv must lie in [0, 1]")


def _batch_size(tensors) -> int:
    sizes = {t.shape[0] for t in tensors if t.dim() == 2}
    if len(sizes) > 1:
        raise ShapeError(f"skin inputs disagree on the batch size: {sorted(sizes)}")
    return sizes.pop() if sizes else 1
