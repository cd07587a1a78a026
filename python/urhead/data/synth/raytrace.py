"""A CPU ray tracer for ground-truth images (Rust, obvhs BVH, rayon over tiles).

It shares no code with the training renderer, so images it makes are an independent
check of the rasterizer's conventions, and it can show what the model cannot represent
exactly: procedural albedo detail evaluated at every hit (pores, mottling, decals such as
freckles, eyebrow hairs, iris and pupil), thin geometry (hair, eyelashes), soft shadows
and a specular lobe. No gradients.

Conventions: the :class:`urhead.Camera` (OpenCV axes, pixel centres at +0.5), both faces
of every triangle visible, barycentrics (u, v) of vertices 1 and 2 as nvdiffrast outputs
them. Deterministic for any thread count (``URHEAD_NUM_THREADS``).
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass
from typing import NamedTuple

import numpy as np

from urhead._threads import num_threads
from urhead.camera import Camera
from urhead.errors import IndexRangeError, InvalidArgumentError, ShapeError
from urhead.head.mesh import vertex_normals_numpy
from urhead.ops._bridge import native


@dataclass(frozen=True)
class Material:
    """Reflectance of a group of faces. Sizes in scene units (metres for heads).

    - ``specular``: weight of the normalised Blinn–Phong lobe; ``shininess`` its exponent.
    - ``wrap`` in [0, 1): diffuse light wraps past the terminator (soft, skin-like).
    - ``pore_strength`` in [0, 1], ``pore_size``: cellular pores (darker, less shiny).
    - ``mottle_strength`` in [0, 1], ``mottle_size``: low-frequency albedo variation.
    - ``textured``: multiply the albedo by ``texture`` at the hit's UV.
    """

    specular: float = 0.0
    shininess: float = 20.0
    wrap: float = 0.0
    pore_strength: float = 0.0
    pore_size: float = 1e-3
    mottle_strength: float = 0.0
    mottle_size: float = 1e-2
    textured: bool = False

    def row(self) -> list[float]:
        return [float(x) for x in astuple(self)]


@dataclass(frozen=True)
class Light:
    """A directional key light of angular radius ``angular_radius`` (radians; soft shadows)
    shining from ``direction`` (towards the light, world space; normalised here), plus a
    hemisphere ambient from ``ambient_down`` to ``ambient_up`` about the world ``up``."""

    direction: tuple = (0.4, 0.6, 0.7)
    color: tuple = (1.0, 1.0, 1.0)
    angular_radius: float = 0.05
    ambient_up: tuple = (0.25, 0.25, 0.27)
    ambient_down: tuple = (0.08, 0.07, 0.07)
    up: tuple = (0.0, 1.0, 0.0)

    def core_args(self) -> tuple:
        def unit(name, v):
            v = np.asarray(v, np.float64)
            n = float(np.linalg.norm(v))
            if v.shape != (3,) or not n > 0 or not math.isfinite(n):
                raise InvalidArgumentError(f"light {name} must be a non-zero 3-vector, got {v}")
            return (v / n).astype(np.float32).tolist()

        def rgb(name, v):
            v = np.asarray(v, np.float32)
            if v.shape != (3,):
                raise ShapeError(f"light {name} must be 3 values, got shape {v.shape}")
            return v.tolist()

        return (
            unit("direction", self.direction),
            rgb("color", self.color),
            float(self.angular_radius),
            rgb("ambient_up", self.ambient_up),
            rgb("ambient_down", self.ambient_down),
            unit("up", self.up),
        )


def decal(a, b=None, *, radius: float, color, opacity: float = 1.0, iris: bool = False):
    """One row of the decal table: a capsule from ``a`` to ``b`` (a sphere if ``b`` is
    None) of ``radius`` in solid coordinates, painting ``color`` with ``opacity`` where the
    surface passes through it (soft-edged). With ``iris``, ``a`` is the iris centre on the
    eyeball and ``b`` the eyeball centre; the colour gets radial fibres and a limbal ring."""
    a = np.asarray(a, np.float32).reshape(3)
    b = a if b is None else np.asarray(b, np.float32).reshape(3)
    return [*a, *b, radius, *np.asarray(color, np.float32).reshape(3), opacity, float(iris)]


class RayTraced(NamedTuple):
    rgb: np.ndarray
    """(H, W, 3) float32 colour, the mean of the samples, composited over the background."""
    alpha: np.ndarray
    """(H, W) float32 fraction of samples that hit the scene."""
    normal: np.ndarray
    """(H, W, 3) float32 unit shading normals in OpenCV camera axes (z < 0 faces the
    camera), normalised mean over the samples that hit; zero where none did."""
    depth: np.ndarray
    """(H, W) float32 linear camera-space depth, mean over the samples that hit; 0 else."""
    face: np.ndarray | None
    """(H, W) int32 face hit by the ray through the pixel centre, −1 for none; this and
    the next two are None when the call passed ``centre_hits=False``."""
    bary: np.ndarray | None
    """(H, W, 2) float32 barycentrics (u, v) of that face's vertices 1 and 2."""
    t: np.ndarray | None
    """(H, W) float32 distance along the unit centre ray to that hit (0 for none)."""


class TriangleBvh:
    """A BVH over a triangle mesh, kept between the frames of an animation whose topology
    never changes.

    ``raytrace(..., bvh=tree)`` refits it to that call's vertices (every bound recomputed,
    the tree's grouping kept) instead of building a new tree: for ~250k triangles about
    0.01 s instead of 0.12 s. The result depends only on the mesh the tree was built from,
    never on earlier frames, so renders stay deterministic; it is exact for any vertices,
    only slower to traverse the further the mesh moves from that shape. Images match
    those of a fresh tree except where two faces are hit at exactly the same distance.

    Args:
        vertices: (V, 3) positions to build the tree over.
        faces: (F, 3) vertex indices; every render given this tree must have F faces.
    """

    def __init__(self, vertices, faces):
        vertices = _vertices(vertices)
        self._core = native("TriangleBvh")(vertices, _faces(faces, len(vertices)))

    @property
    def num_faces(self) -> int:
        return self._core.num_faces


def _vertices(vertices) -> np.ndarray:
    vertices = np.ascontiguousarray(np.asarray(vertices, dtype=np.float32))
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ShapeError(f"vertices must be (N, 3), got {vertices.shape}")
    return vertices


def _faces(faces, num_vertices: int) -> np.ndarray:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise ShapeError(f"faces must be (F, 3) integers, got {faces.shape} {faces.dtype}")
    if len(faces) and (faces.min() < 0 or faces.max() >= num_vertices):
        raise IndexRangeError(
            f"faces must index [0, {num_vertices}), got [{faces.min()}, {faces.max()}]"
        )
    return np.ascontiguousarray(faces, dtype=np.int32)


def raytrace(
    vertices,
    faces,
    camera: Camera,
    *,
    normals=None,
    colors=None,
    solid=None,
    uvs=None,
    texture=None,
    face_material=None,
    materials=(Material(),),
    decals=None,
    light: Light = Light(),
    samples_per_side: int = 4,
    edge_samples_per_side: int = 0,
    shadows: bool = True,
    centre_hits: bool = True,
    background=(1.0, 1.0, 1.0),
    seed: int = 0,
    bvh: TriangleBvh | None = None,
) -> RayTraced:
    """Ray-trace a triangle mesh.

    Args:
        vertices: (V, 3) world positions.
        faces: (F, 3) vertex indices (both faces of a triangle are visible).
        camera: the :class:`urhead.Camera`.
        normals: (V, 3) shading normals; default area-weighted vertex normals.
        colors: (V, 3) albedo in [0, 1]; default 0.8 grey.
        solid: (V, 3) coordinates of the procedural detail (the rest pose, so patterns
            move with the surface); default ``vertices``.
        uvs: (V, 2) texture coordinates and texture (TH, TW, 3), row 0 at v = 1; needed by
            ``textured`` materials.
        face_material: (F,) index into ``materials``; default all 0.
        materials: sequence of :class:`Material`.
        decals: (D, 12) rows made by :func:`decal`, blended in order; default none.
        light: the :class:`Light`.
        samples_per_side: n gives n × n stratified samples per pixel (1: the centre).
        edge_samples_per_side: m > n renders pixels whose first samples disagree
            (coverage, material, or depth spread over 1 %) again with m × m samples.
        shadows: trace shadow rays to the key light.
        centre_hits: also trace the ray through each pixel centre for ``face``, ``bary``
            and ``t`` (one more ray per pixel; without it they are None).
        background: RGB behind the scene.
        seed: seed of the sample jitter.
        bvh: a :class:`TriangleBvh` over ``len(faces)`` faces to refit to ``vertices``
            instead of building a tree (for the frames of an animation).

    Returns:
        :class:`RayTraced` numpy arrays.
    """

    def f32(name, a, cols):
        a = np.ascontiguousarray(np.asarray(a, dtype=np.float32))
        if a.ndim != 2 or a.shape[1] != cols:
            raise ShapeError(f"{name} must be (N, {cols}), got {a.shape}")
        return a

    vertices = _vertices(vertices)
    faces = _faces(faces, len(vertices))
    nv, nf = len(vertices), len(faces)
    if bvh is not None and bvh.num_faces != nf:
        raise InvalidArgumentError(f"bvh was built over {bvh.num_faces} faces, the scene has {nf}")
    if normals is None:
        normals = vertex_normals_numpy(vertices, faces)
    if colors is None:
        colors = np.full((nv, 3), 0.8, np.float32)
    if face_material is None:
        face_material = np.zeros(nf, np.int32)
    table = np.asarray([m.row() for m in materials], np.float32).reshape(-1, 8)
    decal_table = np.zeros((0, 12), np.float32) if decals is None else decals
    out = native("raytrace_render")(
        vertices,
        faces,
        f32("normals", normals, 3),
        f32("colors", colors, 3),
        vertices if solid is None else f32("solid", solid, 3),
        None if uvs is None else f32("uvs", uvs, 2),
        None if texture is None else np.ascontiguousarray(texture, np.float32),
        np.ascontiguousarray(face_material, np.int32),
        table,
        f32("decals", decal_table, 12),
        light.core_args(),
        camera.core_args(),
        int(samples_per_side),
        int(edge_samples_per_side),
        bool(shadows),
        bool(centre_hits),
        [float(c) for c in background],
        int(seed) & 0xFFFFFFFF,
        num_threads(),
        None if bvh is None else bvh._core,
    )
    return RayTraced(*out)
