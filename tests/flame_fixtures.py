"""Synthetic stand-ins for the licensed FLAME files, with their real structure.

A FLAME-sized mesh (5023 vertices, 9976 faces: a capped tube for the head, open at the
neck, plus two closed eyeballs), FLAME's joints and blendshape layout, pickled the way the
official files are: 2020-style by "Python 2" (protocol 2, Python 2 strings and module
names) with chumpy objects carrying chumpy's whole instance state and
``scipy.sparse.csc.csc_matrix`` under its old module path, 2023-style by Python 3 with
chumpy objects and a modern sparse matrix. The classes are stand-ins registered in
``sys.modules`` only while pickling, so neither chumpy nor an old scipy is needed. Also a
matching ``head_template_mesh.obj``.
"""

from __future__ import annotations

import io
import pickle
import struct
import sys
import types
from contextlib import contextmanager
from typing import ClassVar

import numpy as np
import scipy.sparse

from urhead.head.teeth import FLAME_LIP_OUTSIDE_LOWER, FLAME_LIP_OUTSIDE_UPPER

ROWS, COLS = 78, 60  # head tube: 78 rings of 60 + a crown pole = 4681 vertices
EYE_RINGS, EYE_COLS = 13, 13  # each eyeball: 13 rings of 13 + 2 poles = 171 vertices
NUM_SHAPE, NUM_EXPR, NUM_JOINTS = 300, 100, 5


def _tube_faces(rings: int, cols: int, offset: int) -> list:
    faces = []
    for r in range(rings - 1):
        for c in range(cols):
            a, b = offset + r * cols + c, offset + r * cols + (c + 1) % cols
            a2, b2 = a + cols, b + cols
            faces += [[a, a2, b2], [a, b2, b]]
    return faces


def flame_like_mesh():
    """(verts (5023, 3), faces (9976, 3), uv (T, 2), uv_faces (9976, 3), eye_ids (2, 171))."""
    pole = 0
    verts = [[0.0, 0.12, 0.0]]
    uv = []
    theta = np.linspace(0.12, 0.95 * np.pi, ROWS)
    phi = np.linspace(0, 2 * np.pi, COLS, endpoint=False)
    for t in theta:
        for p in phi:
            verts.append(
                [0.09 * np.sin(t) * np.sin(p), 0.12 * np.cos(t), 0.1 * np.sin(t) * np.cos(p)]
            )
    faces = [[pole, 1 + (c + 1) % COLS, 1 + c] for c in range(COLS)]
    faces += _tube_faces(ROWS, COLS, 1)

    # UVs: lat-long with a seam column (COLS + 1 uv columns) and one pole copy per column,
    # kept below v = 0.9 so the teeth box at the top stays empty.
    def head_uv(r, c):
        return [c / COLS, 0.88 * (1 - (r + 1) / ROWS)]

    uv_index = {}
    for r in range(ROWS):
        for c in range(COLS + 1):
            uv_index[(r, c)] = len(uv)
            uv.append(head_uv(r, c))
    pole_uv = []
    for c in range(COLS):
        pole_uv.append(len(uv))
        uv.append([(c + 0.5) / COLS, 0.89])
    uv_faces = [[pole_uv[c], uv_index[(0, c + 1)], uv_index[(0, c)]] for c in range(COLS)]
    for r in range(ROWS - 1):
        for c in range(COLS):
            a, b = uv_index[(r, c)], uv_index[(r, c + 1)]
            a2, b2 = uv_index[(r + 1, c)], uv_index[(r + 1, c + 1)]
            uv_faces += [[a, a2, b2], [a, b2, b]]

    eye_ids = []
    for side, cx in enumerate((0.031, -0.031)):
        base = len(verts)
        centre = np.array([cx, 0.03, 0.07])
        verts.append(centre + np.array([0, 0.012, 0]))
        et = np.linspace(0.3, np.pi - 0.3, EYE_RINGS)
        ep = np.linspace(0, 2 * np.pi, EYE_COLS, endpoint=False)
        for t in et:
            for p in ep:
                verts.append(
                    centre
                    + 0.012 * np.array([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)])
                )
        verts.append(centre - np.array([0, 0.012, 0]))
        top, bottom = base, base + 1 + EYE_RINGS * EYE_COLS
        ring0 = base + 1
        eye_faces = [[top, ring0 + (c + 1) % EYE_COLS, ring0 + c] for c in range(EYE_COLS)]
        eye_faces += _tube_faces(EYE_RINGS, EYE_COLS, ring0)
        last = ring0 + (EYE_RINGS - 1) * EYE_COLS
        eye_faces += [[bottom, last + c, last + (c + 1) % EYE_COLS] for c in range(EYE_COLS)]
        faces += eye_faces
        u0 = 0.02 + 0.5 * side
        for tri in eye_faces:  # one UV per vertex corner, per-vertex planar chart
            ids = []
            for v in tri:
                p = np.asarray(verts[v]) - centre
                ids.append(len(uv))
                uv.append([u0 + 0.2 * (0.5 + p[0] / 0.03), 0.9 + 0.04 * (0.5 + p[1] / 0.03)])
            uv_faces.append(ids)
        eye_ids.append(np.arange(base, len(verts)))

    verts = np.asarray(verts)
    # Put FLAME's lip rings on a mouth: upper lip 4 mm above lower, across 5 cm.
    x = np.linspace(0.025, -0.025, len(FLAME_LIP_OUTSIDE_UPPER))
    z = 0.095 - 8 * x**2
    verts[list(FLAME_LIP_OUTSIDE_UPPER)] = np.stack([x, np.full_like(x, -0.048), z], 1)
    verts[list(FLAME_LIP_OUTSIDE_LOWER)] = np.stack([x, np.full_like(x, -0.052), z], 1)
    return verts, np.asarray(faces), np.clip(np.asarray(uv), 0, 1), np.asarray(uv_faces), eye_ids


def flame_like_model(seed: int = 0) -> dict:
    """The dict a FLAME pickle holds, as plain numpy / scipy values."""
    rng = np.random.default_rng(seed)
    verts, faces, _, _, eye_ids = flame_like_mesh()
    V = len(verts)
    y = verts[:, 1]
    regressor = np.zeros((NUM_JOINTS, V))
    ring = lambda r: 1 + r * COLS + np.arange(COLS)  # noqa: E731
    regressor[0, ring(ROWS - 1)] = 1 / COLS
    regressor[1, ring(ROWS - 12)] = 1 / COLS
    regressor[2, ring(ROWS - 25)] = 1 / COLS
    regressor[3, eye_ids[0]] = 1 / len(eye_ids[0])
    regressor[4, eye_ids[1]] = 1 / len(eye_ids[1])
    weights = np.zeros((V, NUM_JOINTS))
    weights[:, 0] = np.clip((-0.08 - y) / 0.04, 0, 1)
    weights[:, 2] = np.clip((-0.02 - y) / 0.03, 0, 1) * (verts[:, 2] > 0) * (1 - weights[:, 0])
    weights[:, 1] = 1 - weights[:, 0] - weights[:, 2]
    weights[eye_ids[0]] = [0, 0, 0, 1, 0]
    weights[eye_ids[1]] = [0, 0, 0, 0, 1]
    kintree = np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.int64)
    return {
        "v_template": verts,
        "f": faces.astype(np.uint32),
        "shapedirs": rng.normal(0, 1e-3, (V, 3, NUM_SHAPE + NUM_EXPR)),
        "posedirs": rng.normal(0, 1e-4, (V, 3, 9 * (NUM_JOINTS - 1))),
        "J_regressor": scipy.sparse.csc_matrix(regressor),
        "weights": weights,
        "kintree_table": kintree,
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }


def _stand_in(module: str, name: str, getstate=None) -> type:
    """A class that pickles under ``module.name`` (importable only inside
    :func:`_fake_modules`)."""
    body = {"__module__": module, "__qualname__": name}
    if getstate is not None:
        body["__getstate__"] = getstate
    return type(name, (), body)


def chumpy_class(module: str = "chumpy.ch", name: str = "Ch") -> type:
    """A stand-in for a chumpy class whose ``__getstate__`` is chumpy's: the instance dict
    less its weak-reference caches ``_parents`` and ``_cache``."""

    def getstate(self):
        return {k: v for k, v in self.__dict__.items() if k not in ("_parents", "_cache")}

    return _stand_in(module, name, getstate)


def chumpy_object(cls: type, **terms):
    """An instance of a :func:`chumpy_class` with the bookkeeping chumpy's ``Ch.__new__``
    gives every object (a set of dirty terms, the iteration marker, the ``depends_on``
    table, the dense/sparse flags, the weak-reference caches) plus its terms (``x`` for a
    plain ``Ch``)."""
    obj = cls.__new__(cls)
    obj.__dict__.update(
        _dirty_vars=set(terms),
        _itr=None,
        _parents={},
        _cache={"r": None, "drs": {}},
        _depends_on_deps={},
        _make_dense=False,
        _make_sparse=False,
        **terms,
    )
    return obj


class Python2Pickler(pickle._Pickler):
    """Protocol 2 as Python 2 wrote it: text and bytes alike as Python 2 ``str``
    (SHORT_BINSTRING / BINSTRING; no unicode opcodes, no ``_codecs.encode``), builtins
    under ``__builtin__`` and ``copy_reg`` (pickle's ``fix_imports``).
    :func:`python2_pickle` also renames numpy's module to Python 2's
    ``numpy.core.multiarray``."""

    dispatch: ClassVar[dict] = dict(pickle._Pickler.dispatch)

    def save_python2_str(self, obj: bytes | str) -> None:
        raw = obj.encode("latin-1") if isinstance(obj, str) else obj
        n = len(raw)
        if n < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([n]) + raw)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", n) + raw)
        self.memoize(obj)

    dispatch[bytes] = save_python2_str
    dispatch[str] = save_python2_str


def python2_pickle(obj) -> bytes:
    buffer = io.BytesIO()
    Python2Pickler(buffer, protocol=2, fix_imports=True).dump(obj)
    return buffer.getvalue().replace(b"cnumpy._core.multiarray\n", b"cnumpy.core.multiarray\n")


@contextmanager
def _fake_modules(classes):
    saved = {}
    for cls in classes:
        parts = cls.__module__.split(".")
        for k in range(1, len(parts) + 1):  # parents too: pickle imports the dotted path
            name = ".".join(parts[:k])
            if name not in sys.modules or k == len(parts):
                saved.setdefault(name, sys.modules.get(name))
                sys.modules[name] = types.ModuleType(name)
        setattr(sys.modules[cls.__module__], cls.__qualname__, cls)
    try:
        yield
    finally:
        for name, old in saved.items():
            if old is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = old


def pickle_with_stand_ins(obj, classes, python2: bool = True, protocol: int = 2) -> bytes:
    """``obj`` pickled while the stand-in ``classes`` are importable under their names:
    ``python2`` as Python 2 wrote it, else by Python 3 with ``protocol``."""
    with _fake_modules(classes):
        return python2_pickle(obj) if python2 else pickle.dumps(obj, protocol=protocol)


def write_flame2020_pickle(path, model: dict) -> None:
    """As FLAME 2020's ``generic_model.pkl`` is stored: written by Python 2, protocol 2,
    latin-1 strings; chumpy ``Ch`` objects with their whole instance state for the
    template and blendshapes; ``scipy.sparse.csc.csc_matrix`` (old path, old instance
    state) for the regressor."""
    Ch = chumpy_class()
    Csc = _stand_in("scipy.sparse.csc", "csc_matrix")
    out = dict(model)
    for key in ("v_template", "shapedirs", "posedirs"):
        if key in model:
            out[key] = chumpy_object(Ch, x=np.asarray(model[key]))
    out["J_regressor"] = _old_csc(Csc, model["J_regressor"])
    blob = pickle_with_stand_ins(out, [Ch, Csc], python2=True)
    with open(path, "wb") as f:
        f.write(blob)


def write_flame2023_pickle(path, model: dict) -> None:
    """As ``flame2023.pkl``: chumpy ``Ch`` objects with their whole state, written by
    Python 3 (protocol 4: sets as opcodes, str keys), and a modern scipy sparse matrix."""
    Ch = chumpy_class()
    out = dict(model)
    for key in ("v_template", "shapedirs", "posedirs"):
        if key in model:
            out[key] = chumpy_object(Ch, x=np.asarray(model[key]))
    out["J_regressor"] = scipy.sparse.csc_matrix(model["J_regressor"])
    blob = pickle_with_stand_ins(out, [Ch], python2=False, protocol=4)
    with open(path, "wb") as f:
        f.write(blob)


def _old_csc(cls: type, matrix):
    """An instance of an old-scipy ``csc_matrix`` stand-in with that class's state."""
    reg = scipy.sparse.csc_matrix(matrix)
    sparse = cls.__new__(cls)
    sparse.__dict__.update(
        _shape=reg.shape,
        maxprint=50,
        format="csc",
        data=reg.data,
        indices=reg.indices,
        indptr=reg.indptr,
        has_sorted_indices=True,
    )
    return sparse


def write_template_obj(path) -> None:
    verts, faces, uv, uv_faces, _ = flame_like_mesh()
    with open(path, "w") as f:
        f.write("# synthetic head_template_mesh.obj\n")
        f.writelines(f"v {x:.8f} {y:.8f} {z:.8f}\n" for x, y, z in verts)
        f.writelines(f"vt {u:.8f} {v:.8f}\n" for u, v in uv)
        for tri, tt in zip(faces, uv_faces, strict=True):
            f.write(
                "f " + " ".join(f"{a + 1}/{b + 1}" for a, b in zip(tri, tt, strict=True)) + "\n"
            )
