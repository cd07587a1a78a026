"""Loading the official FLAME model files (licensed; users bring their own).

``load_flame`` reads FLAME 2020's ``generic_model.pkl`` or ``flame2023.pkl`` (see
:mod:`urhead.head.pickle_compat` for how the chumpy/scipy pickle is read safely), the UV
layout from ``head_template_mesh.obj``, optionally the part masks of ``FLAME_masks.pkl``,
and appends the VHAP teeth with URHead's fixes (:mod:`urhead.head.teeth`). Convert once
with ``urhead convert-flame`` and use the ``.npz`` from then on.

Without an OBJ the model has **no UV layout** (``has_uv`` is False) and every operation
that needs UVs raises a clear error; we do not invent a layout, because UV maps trained on
a made-up layout would not transfer to FLAME's.

Region labels come from ``FLAME_masks.pkl`` when given. Without it they are estimated:
eyeballs exactly (FLAME's eyeballs are their own connected components), teeth from the
extension, and face / scalp / neck / ears roughly, by position relative to the joints
(documented in :func:`estimate_regions`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from urhead.errors import InvalidArgumentError, ShapeError
from urhead.head.model import REGION_NAMES, HeadModel
from urhead.head.objfile import read_obj
from urhead.head.pickle_compat import ChumpyStub, load_flame_pickle
from urhead.head.teeth import TeethConfig, add_teeth
from urhead.head.uv import seam_free_vertex_uv

FLAME_NUM_SHAPE = 300
REQUIRED_KEYS = (
    "v_template",
    "f",
    "shapedirs",
    "posedirs",
    "J_regressor",
    "weights",
    "kintree_table",
)


def load_flame(
    pkl_path,
    obj_path=None,
    teeth: bool = True,
    masks_path=None,
    num_shape: int = FLAME_NUM_SHAPE,
    teeth_config: TeethConfig | None = None,
) -> HeadModel:
    """A :class:`HeadModel` from the official FLAME files.

    Args:
        pkl_path: ``generic_model.pkl`` (FLAME 2020) or ``flame2023.pkl``.
        obj_path: ``head_template_mesh.obj`` for the UV layout (its faces must equal the
            pickle's); None → no UV layout.
        teeth: append the VHAP teeth rows and the mouth plate (5023 → 5143 vertices).
        masks_path: ``FLAME_masks.pkl`` for the region labels; None → estimated.
        num_shape: how many leading ``shapedirs`` columns are identity (FLAME: 300); the
            rest are expression.
        teeth_config: lip ring ids, proportions and UV box of the teeth (default:
            :class:`TeethConfig`, FLAME's lip rings).
    """
    raw = load_flame_pickle(pkl_path)
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise InvalidArgumentError(f"{pkl_path}: not a FLAME model, missing keys {missing}")
    v_template = _array(raw, "v_template", np.float64)
    _shape(v_template, "v_template", (None, 3))
    V = v_template.shape[0]
    faces = _array(raw, "f", np.int64)
    _shape(faces, "f", (None, 3))
    shapedirs = _array(raw, "shapedirs", np.float64)
    _shape(shapedirs, "shapedirs", (V, 3, None))
    if shapedirs.shape[2] < num_shape:
        raise ShapeError(
            f"shapedirs has {shapedirs.shape[2]} columns, fewer than num_shape={num_shape}"
        )
    posedirs = _array(raw, "posedirs", np.float64)
    _shape(posedirs, "posedirs", (V, 3, None))
    j_regressor = raw["J_regressor"]
    if scipy.sparse.issparse(j_regressor):
        j_regressor = np.asarray(j_regressor.toarray(), np.float64)
    else:
        j_regressor = _array(raw, "J_regressor", np.float64)
    kintree = _array(raw, "kintree_table", np.int64)
    _shape(kintree, "kintree_table", (2, None))
    J = kintree.shape[1]
    _shape(j_regressor, "J_regressor", (J, V))
    weights = _array(raw, "weights", np.float64)
    _shape(weights, "weights", (V, J))
    parents = kintree[0].copy()
    parents[0] = -1  # stored as the largest uint32

    if obj_path is not None:
        uv_coords, uv_faces = _uv_layout(obj_path, V, faces)
        vertex_uv = seam_free_vertex_uv(faces, uv_faces, uv_coords, V)
    else:
        uv_coords, uv_faces, vertex_uv = np.zeros((0, 2)), np.zeros((0, 3), int), np.zeros((0, 2))

    rest_joints = j_regressor @ v_template
    if masks_path is not None:
        regions = regions_from_masks(masks_path, V)
    else:
        regions = estimate_regions(v_template, faces, rest_joints)

    head = HeadModel(
        v_template=v_template,
        faces=faces,
        shapedirs=shapedirs,
        posedirs=posedirs.reshape(-1, posedirs.shape[2]).T,
        j_regressor=j_regressor,
        parents=parents,
        lbs_weights=weights,
        uv_coords=uv_coords,
        uv_faces=uv_faces,
        vertex_uv=vertex_uv,
        vertex_region=regions,
        num_shape=num_shape,
        num_expr=shapedirs.shape[2] - num_shape,
    )
    return add_teeth(head, teeth_config or TeethConfig()) if teeth else head


def regions_from_masks(masks_path, num_vertices: int) -> np.ndarray:
    """(V,) labels from FLAME's ``FLAME_masks.pkl`` (a dict of part name → vertex ids).
    Later parts override earlier ones: scalp (the default), neck/boundary, face, lips,
    ears, eyeballs."""
    masks = load_flame_pickle(masks_path)
    order = (
        ("neck", ("neck", "boundary")),
        ("face", ("face",)),
        ("lips", ("lips",)),
        ("ears", ("left_ear", "right_ear")),
        ("eyes", ("left_eyeball", "right_eyeball")),
    )
    labels = np.full(num_vertices, REGION_NAMES.index("scalp"), np.int32)
    for region, parts in order:
        for part in parts:
            if part not in masks:
                raise InvalidArgumentError(f"{masks_path}: missing part {part!r}")
            ids = np.asarray(masks[part], np.int64).ravel()
            if ids.size and (ids.min() < 0 or ids.max() >= num_vertices):
                raise InvalidArgumentError(f"{masks_path}: part {part!r} indexes past the mesh")
            labels[ids] = REGION_NAMES.index(region)
    return labels


def estimate_regions(v_template, faces, rest_joints) -> np.ndarray:
    """(V,) rough labels without FLAME's masks. Eyes: every connected component but the
    largest (FLAME's eyeballs). The rest by position in units of the interocular distance
    ``d`` from the eyes' midpoint (y up, z forward): neck below a plane through the jaw
    joint that drops towards the front; ears beyond ±1.1 d sideways and behind the jaw
    joint; scalp above 0.9 d or behind −1.0 d; face otherwise."""
    V = v_template.shape[0]
    graph = scipy.sparse.coo_matrix(
        (np.ones(faces.size), (np.repeat(faces[:, 0:1], 3, 1).ravel(), faces.ravel())),
        shape=(V, V),
    )
    _, comp = scipy.sparse.csgraph.connected_components(graph, directed=False)
    largest = np.bincount(comp).argmax()
    eyes_mid = (rest_joints[3] + rest_joints[4]) / 2
    d = max(float(np.linalg.norm(rest_joints[3] - rest_joints[4])), 1e-9)
    p = (v_template - eyes_mid) / d
    jaw = (rest_joints[2] - eyes_mid) / d
    labels = np.full(V, REGION_NAMES.index("face"), np.int32)
    scalp = (p[:, 1] > 0.9) | (p[:, 2] < -1.0)
    ears = (np.abs(p[:, 0]) > 1.1) & (p[:, 2] < jaw[2]) & (np.abs(p[:, 1] - jaw[1]) < 0.7)
    neck = p[:, 1] < jaw[1] - 0.6 - 0.5 * np.clip(p[:, 2] - jaw[2], 0, None)
    labels[scalp] = REGION_NAMES.index("scalp")
    labels[ears] = REGION_NAMES.index("ears")
    labels[neck] = REGION_NAMES.index("neck")
    labels[comp != largest] = REGION_NAMES.index("eyes")
    return labels


def _uv_layout(obj_path, num_vertices, faces):
    obj = read_obj(obj_path)
    if obj.vertices.shape[0] != num_vertices:
        raise ShapeError(
            f"{obj_path}: has {obj.vertices.shape[0]} vertices, the model {num_vertices}"
        )
    if obj.uv_faces.shape[0] == 0:
        raise InvalidArgumentError(f"{obj_path}: its faces carry no vt indices")
    if obj.faces.shape != faces.shape or not np.array_equal(obj.faces, faces):
        raise InvalidArgumentError(
            f"{obj_path}: its faces differ from the model's f ({obj.faces.shape} vs "
            f"{faces.shape}); use the head_template_mesh.obj of the same FLAME release"
        )
    uv = obj.uv_coords
    if uv.size and (uv.min() < 0 or uv.max() > 1):
        raise InvalidArgumentError(f"{obj_path}: vt coordinates must lie in [0, 1]")
    return uv, obj.uv_faces


def _array(raw, key, dtype) -> np.ndarray:
    if isinstance(raw[key], ChumpyStub):
        raise InvalidArgumentError(
            f"FLAME key {key!r} is a {raw[key].chumpy_class} expression, not a stored array "
            "(only chumpy objects holding their array 'x' can be read without chumpy)"
        )
    try:
        return np.asarray(raw[key], dtype=dtype)
    except (TypeError, ValueError) as e:
        raise InvalidArgumentError(f"FLAME key {key!r} is not a numeric array: {e}") from e


def _shape(a: np.ndarray, key: str, shape: tuple) -> None:
    ok = a.ndim == len(shape) and all(
        s is None or s == d for s, d in zip(shape, a.shape, strict=True)
    )
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"FLAME key {key!r} must be {want}, got {a.shape}")
