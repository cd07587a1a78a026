"""Synthetic stand-ins for the licensed FLAME files, with their real structure.

A FLAME-sized mesh (5023 vertices, 9976 faces: a capped tube for the head, open at the
neck, plus two closed eyeballs), FLAME's joints and blendshape layout, pickled the way the
official files are: 2020-style with chumpy objects and ``scipy.sparse.csc.csc_matrix``
under its old module path (the classes are faked in ``sys.modules`` while pickling, so
neither chumpy nor an old scipy is needed), 2023-style with plain arrays and a modern
sparse matrix. Also a matching ``head_template_mesh.obj``.
"""

from __future__ import annotations

import pickle
import sys
import types
from contextlib import contextmanager

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


def _fake_class(module: str, name: str):
    cls = type(name, (), {"__module__": module, "__qualname__": name})
    return cls


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


def write_flame2020_pickle(path, model: dict) -> None:
    """As FLAME 2020 stores it: chumpy ``Ch`` objects (array in the state under ``x``) for
    the template and blendshapes, ``scipy.sparse.csc.csc_matrix`` (old path, old state
    keys) for the regressor, protocol 2."""
    Ch = _fake_class("chumpy.ch", "Ch")
    Csc = _fake_class("scipy.sparse.csc", "csc_matrix")
    out = dict(model)
    for key in ("v_template", "shapedirs", "posedirs"):
        ch = Ch()
        ch.__dict__.update({"x": np.asarray(model[key]), "_depends_on_deps": {}, "_cache": {}})
        out[key] = ch
    reg = scipy.sparse.csc_matrix(model["J_regressor"])
    sparse = Csc()
    sparse.__dict__.update(
        {
            "_shape": reg.shape,
            "maxprint": 50,
            "format": "csc",
            "data": reg.data,
            "indices": reg.indices,
            "indptr": reg.indptr,
        }
    )
    out["J_regressor"] = sparse
    with _fake_modules([Ch, Csc]), open(path, "wb") as f:
        pickle.dump(out, f, protocol=2)


def write_flame2023_pickle(path, model: dict) -> None:
    """As flame2023.pkl: plain arrays and a modern scipy sparse matrix."""
    out = dict(model)
    out["J_regressor"] = scipy.sparse.csc_matrix(model["J_regressor"])
    with open(path, "wb") as f:
        pickle.dump(out, f, protocol=4)


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
