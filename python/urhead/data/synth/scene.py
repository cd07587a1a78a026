"""The static look of a synthetic subject, built once: a Loop-subdivided copy of the head
with per-vertex albedo and materials, wrinkle fields (true displacement, driven by the
expression), hair volume, hair strands and eyelashes attached to the skin, and decals
(eyebrow hairs, freckles, a mole, irises and pupils) evaluated by the ray tracer at every
hit. All positions are in the rest pose with the subject's identity (the "solid" space
the ray tracer's procedural detail lives in).

The hair comes in three kinds (``HAIR_MODES``), all drawn from the same random numbers so
that they share identity, look and performance and differ only in the hair: ``strands``
(a volume over the scalp with strands and eyelashes on it), ``shell`` (the same volume,
a surface up to 9 mm off the scalp, with the eyelashes and without strands) and ``none``
(the hair only painted on the scalp: nothing off the FLAME surface, eyelashes dropped
too, so it is the oracle of geometry the mesh can represent)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from urhead.data.synth.raytrace import Material, decal
from urhead.data.synth.subdivision import subdivide
from urhead.head.mesh import vertex_normal_operator, vertex_normals_numpy
from urhead.head.model import HeadModel, region_index

# Material ids (rows of MATERIALS).
SKIN, LIPS, EYE, MOUTH, TEETH, HAIR, STRAND, LASH = range(8)
HAIR_MODES = ("none", "shell", "strands")
MATERIALS = (
    Material(
        specular=0.22,
        shininess=28,
        wrap=0.25,
        pore_strength=0.35,
        pore_size=9e-4,
        mottle_strength=0.12,
        mottle_size=0.012,
    ),
    Material(
        specular=0.35,
        shininess=45,
        wrap=0.25,
        pore_strength=0.15,
        pore_size=6e-4,
        mottle_strength=0.1,
        mottle_size=0.004,
    ),
    Material(specular=0.9, shininess=600, wrap=0.0),
    Material(specular=0.1, shininess=20, wrap=0.2),
    Material(specular=0.3, shininess=60, wrap=0.1),
    Material(specular=0.25, shininess=24, wrap=0.1, mottle_strength=0.45, mottle_size=0.0025),
    Material(specular=0.35, shininess=30, wrap=0.2, mottle_strength=0.2, mottle_size=0.01),
    Material(specular=0.1, shininess=20, wrap=0.1),
)


@dataclass
class Strands:
    """Thin curves attached to skin vertices, rebuilt per frame as camera-facing ribbons.

    ``anchor`` (N,) vertex of the coarse head each strand follows (position and skinning
    rotation); ``offsets`` (N, K, 3) the strand's points relative to the anchor in the
    rest pose; ``width`` (N,) in metres; ``color`` (N, 3)."""

    anchor: np.ndarray
    offsets: np.ndarray
    width: np.ndarray
    color: np.ndarray
    material: int

    def __len__(self):
        return len(self.anchor)


@dataclass
class SubjectLook:
    shape: np.ndarray  # (num_shape,) identity coefficients
    rest: np.ndarray  # (V, 3) coarse rest vertices with identity
    S: object  # (Vs, V) sparse subdivision operator
    faces: np.ndarray  # (Fs, 3)
    normal_op: object  # (Vs, Fs)
    solid: np.ndarray  # (Vs, 3) rest positions of the subdivided vertices
    colors: np.ndarray  # (Vs, 3)
    face_material: np.ndarray  # (Fs,)
    static_offset: np.ndarray  # (Vs,) metres along the normal: hair volume, micro relief
    wrinkle_fields: dict  # name → (Vs,) metres along the normal at full activation
    decals: np.ndarray  # (D, 12)
    strands: list  # [Strands]


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)


def _landmarks(head: HeadModel, rest: np.ndarray, joints: np.ndarray) -> dict:
    face = rest[head.region_vertices("face")]
    lips = rest[head.region_vertices("lips")]
    eyes = rest[head.region_vertices("eyes")]
    centre_l, centre_r = joints[3], joints[4]
    eye_radius = float(np.median(np.linalg.norm(eyes - centre_l, axis=1)[eyes[:, 0] > 0]))
    front = face[np.abs(face[:, 0]) < 0.008]
    nose_tip = front[np.argmax(front[:, 2])]
    return {
        "eye_l": centre_l,
        "eye_r": centre_r,
        "eye_radius": eye_radius,
        "mouth_l": lips[np.argmax(lips[:, 0])],
        "mouth_r": lips[np.argmin(lips[:, 0])],
        "mouth_y": float(np.median(lips[:, 1])),
        "nose_tip": nose_tip,
    }


def _surface_point(tree: cKDTree, verts: np.ndarray, xy: np.ndarray):
    """The front-most surface vertex under each (x, y): the nearest of the front vertices
    in the x–y plane."""
    _, idx = tree.query(xy)
    return verts[idx]


def build_look(
    head: HeadModel,
    rng: np.random.Generator,
    *,
    levels: int,
    hair_strands: int,
    wrinkle_scale: float,
    hair: str = "strands",
) -> SubjectLook:
    import torch

    if hair not in HAIR_MODES:
        raise ValueError(f"hair must be one of {HAIR_MODES}, got {hair!r}")

    num_named = 12
    shape = np.zeros(head.num_shape, np.float32)
    shape[:num_named] = rng.uniform(-1.2, 1.2, size=min(num_named, head.num_shape))
    shape[num_named:] = rng.normal(scale=0.5, size=head.num_shape - num_named)
    skinned = head.skin(shape=torch.from_numpy(shape))
    rest = skinned.verts[0].double().numpy()
    joints = skinned.joints[0].double().numpy()
    marks = _landmarks(head, rest, joints)

    S, faces, parent = subdivide(head.faces, head.num_vertices, levels)
    solid = (S @ rest).astype(np.float32)
    region = head.vertex_region
    face_region = head.face_region()[parent]
    to_material = {
        "face": SKIN,
        "neck": SKIN,
        "ears": SKIN,
        "scalp": HAIR,
        "lips": LIPS,
        "eyes": EYE,
        "mouth_interior": MOUTH,
        "teeth": TEETH,
    }
    material_of_region = np.zeros(8, np.int32)
    for name, m in to_material.items():
        material_of_region[region_index(name)] = m
    face_material = material_of_region[face_region]

    # --- albedo per coarse vertex, smoothed by the subdivision --------------------------
    tone = np.array([0.78, 0.56, 0.45]) * rng.uniform(0.85, 1.1)
    hair_color = np.array([0.16, 0.10, 0.06]) * rng.uniform(0.6, 1.6)
    palette = {
        "face": tone,
        "neck": tone * 0.96,
        "ears": tone * np.array([1.02, 0.93, 0.9]),
        "scalp": hair_color,
        "lips": np.array([0.66, 0.32, 0.3]),
        "eyes": np.array([0.9, 0.88, 0.85]),
        "mouth_interior": np.array([0.45, 0.16, 0.15]),
        "teeth": np.array([0.88, 0.85, 0.76]),
    }
    colors = np.zeros((head.num_vertices, 3))
    for name, c in palette.items():
        colors[region == region_index(name)] = c
    skinlike = np.isin(region, [region_index(n) for n in ("face", "neck", "ears")])
    for side in (1, -1):  # cheek flush
        centre = marks["eye_l"] * np.array([side, 1, 1]) + np.array([0.005 * side, -0.035, 0.01])
        w = np.exp(-np.sum((rest - centre) ** 2, 1) / (2 * 0.014**2)) * skinlike
        colors += w[:, None] * np.array([0.06, -0.04, -0.03])
    colors = np.clip(S @ colors, 0, 1).astype(np.float32)

    # --- displacement: hair volume, micro relief, wrinkle fields -------------------------
    tree_face = cKDTree(rest[region == region_index("face")])
    dist_to_face, _ = tree_face.query(rest)
    scalp = (region == region_index("scalp")).astype(float)
    hair_thickness = scalp * 0.009 * _smoothstep(0.0, 0.02, dist_to_face)
    volume = hair_thickness if hair != "none" else np.zeros_like(hair_thickness)
    static = S @ volume
    p = solid.astype(np.float64)
    waves = rng.normal(size=(24, 3))
    waves *= (2 * np.pi / rng.uniform(0.002, 0.006, size=24))[:, None] / np.linalg.norm(
        waves, axis=1, keepdims=True
    )
    phase = rng.uniform(0, 2 * np.pi, 24)
    skin_sub = S @ skinlike.astype(float)
    static = static + 4e-5 * skin_sub * np.sin(p @ waves.T + phase).sum(1) / np.sqrt(24)

    fields = _wrinkle_fields(p, marks, skin_sub, rng)
    fields = {k: (v * wrinkle_scale).astype(np.float32) for k, v in fields.items()}

    # --- decals --------------------------------------------------------------------------
    front_ids = np.flatnonzero(
        (region == region_index("face")) & (rest[:, 2] > marks["eye_l"][2] - 0.03)
    )
    front = rest[front_ids]
    tree_front = cKDTree(front[:, :2])
    rows = []
    brow_color = hair_color * 0.8
    for side in (1, -1):
        eye = marks["eye_l"] if side > 0 else marks["eye_r"]
        for _ in range(170):
            s = rng.uniform(0, 1)
            x = eye[0] + side * (-0.012 + 0.038 * s)
            y = (
                eye[1]
                + 0.021
                + 0.006 * np.sin(np.pi * s)
                + rng.normal(scale=0.0022) * (1 - 0.5 * s)
            )
            a = _surface_point(tree_front, front, np.array([x, y]))
            direction = np.array([side * (0.8 + 0.2 * s), 0.35 - 0.5 * s, 0.0])
            direction = direction / np.linalg.norm(direction) * rng.uniform(0.003, 0.006)
            b = _surface_point(tree_front, front, (a + direction)[:2])
            rows.append(
                decal(a, b, radius=1.8e-4, color=brow_color, opacity=rng.uniform(0.6, 0.95))
            )
    # Freckles over the nose and cheeks, and one mole.
    for _ in range(int(rng.integers(90, 160))):
        xy = (
            marks["nose_tip"][:2]
            + rng.normal(size=2) * np.array([0.022, 0.012])
            + np.array([0, 0.012])
        )
        c = _surface_point(tree_front, front, xy)
        shade = tone * rng.uniform(0.5, 0.72)
        rows.append(
            decal(c, radius=rng.uniform(4e-4, 1.1e-3), color=shade, opacity=rng.uniform(0.35, 0.7))
        )
    mole_xy = np.array([marks["mouth_l"][0] + 0.012, marks["mouth_y"] + 0.018])
    rows.append(
        decal(
            _surface_point(tree_front, front, mole_xy),
            radius=1.4e-3,
            color=(0.22, 0.13, 0.1),
            opacity=0.95,
        )
    )
    # Irises and pupils: on the eyeball's front in its rest frame (they turn with it).
    iris_color = np.array([0.25, 0.38, 0.5]) * rng.uniform(0.7, 1.3, size=3)
    r = marks["eye_radius"]
    for eye in (marks["eye_l"], marks["eye_r"]):
        front_point = eye + np.array([0, 0, r])
        rows.append(
            decal(
                front_point,
                eye,
                radius=0.48 * r,
                color=np.clip(iris_color, 0, 1),
                opacity=1.0,
                iris=True,
            )
        )
        rows.append(decal(front_point, radius=0.19 * r, color=(0.02, 0.02, 0.02), opacity=1.0))
    decals = np.asarray(rows, np.float32)

    # Both kinds of strands are always drawn, so the random numbers that follow (the
    # performance, the tracking noise) do not depend on the hair mode.
    combed = _hair(head, rest, region, dist_to_face, hair_thickness, hair_color, rng, hair_strands)
    lashes = _lashes(head, rest, region, marks, rng)
    strands = {"none": [], "shell": [lashes], "strands": [combed, lashes]}[hair]
    return SubjectLook(
        shape=shape,
        rest=rest.astype(np.float32),
        S=S,
        faces=faces,
        normal_op=vertex_normal_operator(faces, S.shape[0]),
        solid=solid,
        colors=colors,
        face_material=face_material.astype(np.int32),
        static_offset=static.astype(np.float32),
        wrinkle_fields=fields,
        decals=decals,
        strands=strands,
    )


def _crease(distance, width):
    return np.exp(-((distance / width) ** 2))


def _wrinkle_fields(p, marks, skin, rng) -> dict:
    """Displacements (metres, negative into the skin) at full activation of each driver."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    eye_l, eye_r, r = marks["eye_l"], marks["eye_r"], marks["eye_radius"]
    eye_y, eye_z = eye_l[1], eye_l[2]
    frontal = _smoothstep(eye_z - 0.045, eye_z - 0.02, z) * skin

    # Forehead: horizontal creases 6–8 mm apart, gently wavy, across the brow.
    brow_y = eye_y + 0.024
    wavy = y + 0.0015 * np.sin(x * 70 + rng.uniform(0, 6)) + 0.004 * (x / 0.05) ** 2
    spacing = 0.0068
    u = (wavy - brow_y - 0.008) / spacing
    depth = _crease((u - np.round(u)) * spacing, 7e-4)
    window = (
        _smoothstep(brow_y + 0.004, brow_y + 0.012, y)
        * (1 - _smoothstep(brow_y + 0.045, brow_y + 0.06, y))
        * (1 - _smoothstep(0.035, 0.05, np.abs(x)))
    )
    forehead = -6e-4 * depth * window * frontal

    # Frown lines: two short vertical creases between the brows.
    glabella = np.zeros_like(x)
    for side in (1, -1):
        d = np.abs(x - side * 0.0055 - 0.08 * side * (y - brow_y))
        win = _smoothstep(brow_y - 0.012, brow_y - 0.004, y) * (
            1 - _smoothstep(brow_y + 0.01, brow_y + 0.02, y)
        )
        glabella -= 7e-4 * _crease(d, 6e-4) * win * frontal

    # Crow's feet: three creases fanning from each outer eye corner (smile, squint).
    crows = np.zeros_like(x)
    for eye, side in ((eye_l, 1), (eye_r, -1)):
        corner = eye + np.array([side * (r + 0.004), 0, 0])
        dx, dy = side * (x - corner[0]), y - corner[1]
        dist = np.hypot(dx, dy)
        angle = np.arctan2(dy, dx)
        for a0 in (-0.45, 0.0, 0.4):
            crows -= (
                4.5e-4
                * _crease(np.abs(angle - a0) * dist, 5e-4)
                * _smoothstep(0.002, 0.005, dist)
                * (1 - _smoothstep(0.012, 0.02, dist))
                * (dx > 0)
            )
    crows *= skin

    # Nasolabial folds: from beside the nose wing to outside the mouth corner (smile).
    folds = np.zeros_like(x)
    for mouth, side in ((marks["mouth_l"], 1), (marks["mouth_r"], -1)):
        a = np.array([side * 0.02, marks["nose_tip"][1] + 0.004])
        b = np.array([mouth[0] + side * 0.007, mouth[1] - 0.008])
        ab = b - a
        q = np.stack([x, y], 1) - a
        s = np.clip(q @ ab / (ab @ ab), 0, 1)
        d = np.linalg.norm(q - s[:, None] * ab, axis=1)
        folds -= 1.3e-3 * _crease(d, 1.8e-3) * np.sin(np.pi * s) ** 0.5
    folds *= frontal
    return {
        "brow_raise": forehead,
        "frown": glabella,
        "smile": folds + 0.5 * crows,
        "squint": crows,
    }


def _hair(head, rest, region, dist_to_face, thickness, hair_color, rng, count) -> Strands:
    """Short strands combed back and down over the hair volume, denser near the hairline."""
    scalp = np.flatnonzero(region == region_index("scalp"))
    if count == 0 or scalp.size == 0:
        return Strands(
            np.zeros(0, np.int64),
            np.zeros((0, 5, 3), np.float32),
            np.zeros(0),
            np.zeros((0, 3)),
            STRAND,
        )
    weight = 0.4 + _smoothstep(0.0, 0.04, 0.05 - dist_to_face[scalp])
    anchor = rng.choice(scalp, size=count, p=weight / weight.sum())
    normals = _rest_normals(head, rest)[anchor]
    root = rest[anchor] + normals * (thickness[anchor, None] - 0.0005)
    comb = np.array([0.0, -0.45, -1.0])
    comb = comb - (normals @ comb)[:, None] * normals
    comb += rng.normal(scale=0.35, size=comb.shape)
    comb -= (np.sum(comb * normals, 1))[:, None] * normals
    comb /= np.linalg.norm(comb, axis=1, keepdims=True)
    length = rng.uniform(0.015, 0.04, size=count)
    k = np.linspace(0, 1, 5)
    lift = 0.0015 * np.sin(np.pi * k)[None, :, None] * normals[:, None]
    droop = -0.25 * (k**2)[None, :, None] * length[:, None, None] * normals[:, None]
    points = (
        root[:, None] + (k[None, :, None] * length[:, None, None]) * comb[:, None] + lift + droop
    )
    offsets = points - rest[anchor][:, None]
    color = hair_color[None] * rng.uniform(0.7, 1.5, size=(count, 1))
    width = rng.uniform(2.5e-4, 4.5e-4, size=count)
    return Strands(anchor, offsets.astype(np.float32), width, np.clip(color, 0, 1), STRAND)


def _lashes(head, rest, region, marks, rng) -> Strands:
    """Upper lashes on the lid margin: the face vertices just above each eyeball's front,
    curling out and up."""
    face = np.flatnonzero(region == region_index("face"))
    anchors, offsets = [], []
    r = marks["eye_radius"]
    for eye in (marks["eye_l"], marks["eye_r"]):
        d = rest[face] - eye
        dist = np.linalg.norm(d, axis=1)
        on_rim = (dist < r + 0.004) & (d[:, 1] > 0.1 * r) & (d[:, 2] > 0.45 * r)
        rim = face[on_rim]
        if rim.size == 0:
            continue
        picks = rng.choice(rim, size=70)
        for v in picks:
            base = rest[v] - eye
            out = base / np.linalg.norm(base)
            up = np.array([0, 1, 0.0])
            k = np.linspace(0, 1, 4)[:, None]
            length = rng.uniform(0.006, 0.009)
            curve = (0.6 * out + 0.5 * np.array([0, 0, 1.0])) * k * length + up * (
                k**2
            ) * length * 0.8
            anchors.append(v)
            offsets.append(curve)
    if not anchors:
        return Strands(
            np.zeros(0, np.int64),
            np.zeros((0, 4, 3), np.float32),
            np.zeros(0),
            np.zeros((0, 3)),
            LASH,
        )
    n = len(anchors)
    return Strands(
        np.asarray(anchors),
        np.asarray(offsets, np.float32),
        np.full(n, 1.2e-4),
        np.tile([[0.05, 0.04, 0.035]], (n, 1)),
        LASH,
    )


def _rest_normals(head, rest):
    return vertex_normals_numpy(rest, head.faces)
