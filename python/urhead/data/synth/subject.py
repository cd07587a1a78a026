"""Synthetic ground-truth subjects: the built-in procedural head, made richer than the model
can represent (wrinkles as true displacement of a Loop-subdivided surface, albedo detail
finer than any UV map, hair and eyelashes off the FLAME surface, a specular light),
performing a talking, expressive sequence with head turns up to ±35° yaw, ray-traced by
:mod:`urhead.data.synth.raytrace` and written in the VHAP / GaussianAvatars layout with noisy
("tracked") FLAME parameters and ground-truth normal maps.

Three conditions the model cannot follow exactly can each be set apart, so that each and
its remedy is measured against its oracle: the light (``key``, ``soft``, ``flat``), the
hair (``strands``, ``shell``, ``none``) and the tracking noise (a scale; 0 writes the
exact parameters). The difficulty presets supply them unless given explicitly.

Also written: ``head.npz`` (the head model the FLAME parameters refer to),
``synthetic_ground_truth.npz`` (the exact parameters), ``synthetic.json`` (settings, the
cache key), ``manifest.json`` (every file's size and SHA-256, written last). ``urhead synth
--out DIR`` reuses ``DIR`` when its cache key matches and its files match the manifest.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from urhead.camera import Camera
from urhead.data.background import parse_background
from urhead.data.manifest import MANIFEST, manifest_problem, write_manifest
from urhead.data.synth.motion import FPS, MOTIONS, performance, tracking_noise
from urhead.data.synth.raytrace import Light, TriangleBvh, raytrace
from urhead.data.synth.scene import HAIR_MODES, MATERIALS, Strands, SubjectLook, build_look
from urhead.data.writer import SubjectWriter
from urhead.head.mesh import vertex_normals_numpy

GENERATOR_VERSION = 3
"""Bump when the generator's output changes: it is part of the cache key."""

log = logging.getLogger("urhead.synth")

HEAD_SEED = 0
"""The subjects use the default built-in head (``procedural_head(0)``), as the fit does."""

CAPTURE_TRACKING_NOISE = 0.26
"""The tracking-noise scale of a plausible capture: a mean face-vertex displacement of
about 1 px at 512² (1.00 px mean, 2.4 px on the worst frame, 5.2 px at most over the 600
frames of seed 0; 0.9–1.1 px mean for other seeds and lengths). Landmark fits alone leave
a few pixels (detectors err by ~2–4 % of the inter-ocular distance, ~100 px between the
eye centres here); trackers that add a dense photometric term, such as VHAP, typically
bring the reprojection error to about a pixel. Scale 1 (``hard``) leaves 3.9 px mean,
9.1 px on the worst frame."""

CONDITIONS = ("light", "hair", "tracking_noise")
"""The SynthConfig fields a difficulty supplies unless they are given."""

DIFFICULTIES = {
    # The performance and look: max yaw, expression scale, wrinkle scale, strands drawn,
    # subdivision levels; then the conditions.
    "easy": dict(
        max_yaw_deg=15.0, expression_scale=0.6, wrinkles=0.6, strands=800, levels=1,
        light="key", hair="strands", tracking_noise=0.5,
    ),
    # A plausible capture: light as indoors, short hair (a shell over the scalp, as most
    # subjects of head-avatar datasets have short or tied hair; loose strands off the
    # silhouette are the hard case), tracking noise as a photometric tracker leaves. Its
    # identity, look and performance are those of "hard" (same random draws).
    "default": dict(
        max_yaw_deg=35.0, expression_scale=1.0, wrinkles=1.0, strands=2500, levels=2,
        light="soft", hair="shell", tracking_noise=CAPTURE_TRACKING_NOISE,
    ),
    # The default subject of generator version 2: every condition strong.
    "hard": dict(
        max_yaw_deg=35.0, expression_scale=1.0, wrinkles=1.0, strands=2500, levels=2,
        light="key", hair="strands", tracking_noise=1.0,
    ),
    "extreme": dict(
        max_yaw_deg=35.0, expression_scale=1.3, wrinkles=1.4, strands=5000, levels=2,
        light="key", hair="strands", tracking_noise=2.0,
    ),
}  # fmt: skip

_KEY_DIRECTION = (0.45, 0.55, 0.7)
LIGHTS = {
    # A studio key light fixed in the world: a small source (0.06 rad) casting hard
    # shadows of nose and jaw, with a strong specular, over a dim ambient.
    "key": Light(
        direction=_KEY_DIRECTION,
        color=(1.05, 1.0, 0.95),
        angular_radius=0.06,
        ambient_up=(0.3, 0.31, 0.34),
        ambient_down=(0.12, 0.1, 0.09),
    ),
    # Indoor footage: from the same side, a large source (0.2 rad: a 1 m window 2.5 m
    # away) giving soft shadows, half the directional light, and twice the ambient (the
    # room and sky). A larger source would need more samples: at 0.2 rad, 2 × 2 samples
    # a pixel leave noise like the key's (RMS 0.018 against 6 × 6 samples, key 0.017;
    # 0.35 rad leaves 0.024, mostly diffuse and specular varying over the source).
    "soft": Light(
        direction=_KEY_DIRECTION,
        color=(0.52, 0.5, 0.48),
        angular_radius=0.2,
        ambient_up=(0.6, 0.61, 0.63),
        ambient_down=(0.34, 0.32, 0.3),
    ),
    # Even light, the oracle: a uniform ambient and nothing directional, so every pixel
    # shows its albedo whatever the pose (no shading, shadows or specular), at the mean
    # exposure of the head under key and soft (0.78 and 0.76 of the albedo).
    "flat": Light(
        direction=(0.0, 0.0, 1.0),
        color=(0.0, 0.0, 0.0),
        angular_radius=0.0,
        ambient_up=(0.77, 0.77, 0.77),
        ambient_down=(0.77, 0.77, 0.77),
    ),
}
BACKGROUND = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class SynthConfig:
    """What a synthetic subject is made from; every field enters the cache key."""

    frames: int = 600
    resolution: int = 512
    seed: int = 0
    difficulty: str = "default"
    samples_per_side: int = 2
    edge_samples_per_side: int = 3
    test_last: int | None = None
    # The conditions (see CONDITIONS); None takes the difficulty's.
    light: str | None = None
    hair: str | None = None
    tracking_noise: float | None = None
    background: tuple[float, float, float] = BACKGROUND
    """RGB in [0, 1] the frames are composited on."""
    motion: str = "talking"
    """The performance: ``talking``, or remade as ``extreme`` poses or ``off_screen`` (see
    :data:`urhead.data.synth.motion.MOTIONS`)."""
    length_unit: float = 1.0
    """Metres per length unit of the written files (head model, cameras, FLAME
    translations): 1e-3 writes millimetres, 1e3 kilometres. The images do not change."""

    def __post_init__(self):
        if self.difficulty not in DIFFICULTIES:
            raise ValueError(
                f"difficulty must be one of {sorted(DIFFICULTIES)}, got {self.difficulty!r}"
            )
        if self.frames < 2:
            raise ValueError(f"frames must be >= 2, got {self.frames}")
        if not 16 <= self.resolution <= 4096:
            raise ValueError(f"resolution must be in [16, 4096], got {self.resolution}")
        if self.light not in (None, *LIGHTS):
            raise ValueError(f"light must be one of {sorted(LIGHTS)}, got {self.light!r}")
        if self.hair not in (None, *HAIR_MODES):
            raise ValueError(f"hair must be one of {list(HAIR_MODES)}, got {self.hair!r}")
        if self.tracking_noise is not None and not 0 <= self.tracking_noise < float("inf"):
            raise ValueError(f"tracking_noise must be >= 0, got {self.tracking_noise}")
        if self.motion not in MOTIONS:
            raise ValueError(f"motion must be one of {list(MOTIONS)}, got {self.motion!r}")
        if not 0 < self.length_unit < float("inf"):
            raise ValueError(f"length_unit must be > 0, got {self.length_unit}")

    def resolved(self) -> SynthConfig:
        """This config with the conditions left None taken from its difficulty."""
        preset = DIFFICULTIES[self.difficulty]
        given = {name: getattr(self, name) for name in CONDITIONS}
        values = {name: preset[name] if v is None else v for name, v in given.items()}
        return replace(self, **{**values, "tracking_noise": float(values["tracking_noise"])})

    def cache_key(self) -> str:
        """The same for configs that make the same subject (conditions resolved); white,
        talking, metric subjects keep the keys they had before those were options."""
        settings = asdict(self.resolved())
        for name, default in (("background", BACKGROUND), ("motion", "talking")):
            if settings[name] == default:
                del settings[name]
        if self.length_unit == 1.0:
            del settings["length_unit"]
        blob = json.dumps({"generator_version": GENERATOR_VERSION, **settings}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]


def subject_camera(resolution: int) -> Camera:
    """The fixed camera: 0.75 m in front of the face, a 26° vertical field of view and a
    principal point a little off centre (as a calibrated camera has)."""
    cam = Camera.look_at(
        (0.0, 0.0, 0.75),
        (0.0, -0.012, 0.0),
        fov_y_degrees=26.0,
        width=resolution,
        height=resolution,
    )
    k = cam.K.clone()
    k[0, 2] += 0.006 * resolution
    k[1, 2] -= 0.004 * resolution
    return Camera(k, cam.viewmat, resolution, resolution)


def synthesize(
    out: str | Path,
    config: SynthConfig = SynthConfig(),
    *,
    progress: bool = True,
    force: bool = False,
) -> Path:
    """Make (or reuse) the synthetic subject ``config`` at ``out``; returns ``out``.

    A folder holding a subject with the same cache key is reused as it is once every file
    matches the manifest written with it (sizes and SHA-256); a damaged one is made
    again. Any other existing folder is replaced only with ``force`` or when it is an
    older synthetic subject (it has ``synthetic.json``)."""
    from tqdm import tqdm

    from urhead.head import procedural_head, save_head
    from urhead.head.procedural import EXPRESSION_NAMES

    out = Path(out)
    config = config.resolved()
    key = config.cache_key()
    meta_path = out / "synthetic.json"
    if _key_at(out) == key:
        problem = manifest_problem(out)
        if problem is None:
            return out
        log.warning("%s: the cached subject is damaged (%s); making it again", out, problem)
    if out.exists() and not (force or meta_path.is_file()):
        raise FileExistsError(
            f"{out}: exists and is not a synthetic subject (pass force=True / --force)"
        )

    preset = DIFFICULTIES[config.difficulty]
    rng = np.random.default_rng(config.seed)
    head = procedural_head(HEAD_SEED)
    look = build_look(
        head,
        rng,
        levels=preset["levels"],
        hair_strands=preset["strands"],
        wrinkle_scale=preset["wrinkles"],
        hair=config.hair,
    )
    perf = performance(
        rng,
        config.frames,
        tuple(EXPRESSION_NAMES),
        head.num_expr,
        max_yaw_deg=preset["max_yaw_deg"],
        expression_scale=preset["expression_scale"],
    )
    if MOTIONS[config.motion] is not None:
        perf = MOTIONS[config.motion](perf)
    tracked = tracking_noise(rng, perf, look.shape, config.tracking_noise)
    shape_n, expr_n, pose_n, transl_n = tracked
    camera = subject_camera(config.resolution)
    tables = head.lbs_tables(torch.float32)
    exact = (look.shape, perf.expr, perf.pose, perf.transl)
    displacement = face_displacement(head, tables, camera, exact, tracked)
    renderer = _FrameRenderer(look, camera, config)

    def skin(t: int):
        betas = torch.from_numpy(np.concatenate([look.shape, perf.expr[t]])[None])
        return _lbs(tables, betas, perf.pose[t], perf.transl[t])

    def scene(t: int, skinned) -> _Scene:
        return renderer.scene(skinned, {k: float(v[t]) for k, v in perf.activation.items()}, t)

    def write(t: int, rgb: np.ndarray, mask: np.ndarray, normals: np.ndarray) -> None:
        writer.add_frame(t, np.clip(rgb, 0, 1), mask, flame(t), normals=normals)

    to_unit = 1.0 / config.length_unit

    def flame(t: int) -> dict:
        return {
            "translation": transl_n[t][None] * to_unit,
            "rotation": pose_n[t, 0:3][None],
            "neck_pose": pose_n[t, 3:6][None],
            "jaw_pose": pose_n[t, 6:9][None],
            "eyes_pose": pose_n[t, 9:15][None],
            "shape": shape_n,
            "expr": expr_n[t][None],
        }

    written_camera = Camera(
        camera.K, _scaled_translation(camera.viewmat, to_unit), camera.width, camera.height
    )
    with SubjectWriter(out, written_camera, overwrite=True, test_last=config.test_last) as writer:
        save_head(scaled_head(head, to_unit), writer.staging / "head.npz")
        np.savez(
            writer.staging / "synthetic_ground_truth.npz",
            shape=look.shape,
            expr=perf.expr,
            pose=perf.pose,
            transl=perf.transl * to_unit,
        )
        frames = tqdm(total=config.frames, desc="urhead synth", unit="frame", disable=not progress)
        # A pipeline that keeps every core busy: while frame t is ray-traced (Rust, GIL
        # released, all threads), a helper thread builds frame t + 1's mesh and writes frame
        # t − 1. Frames are still made and written in order, each from its own inputs
        # only, so the bytes do not depend on the timing. The skinning stays on this
        # thread: its kernel shares the tracer's thread pool, where a job sent from the
        # helper would wait for the whole trace.
        with ThreadPoolExecutor(max_workers=1) as helper, frames:
            next_scene = helper.submit(scene, 0, skin(0))
            written = None
            for t in range(config.frames):
                current = next_scene.result()
                if t + 1 < config.frames:
                    next_scene = helper.submit(scene, t + 1, skin(t + 1))
                rgb, mask, normals = renderer.render(current, t)
                if written is not None:
                    written.result()
                    frames.update()
                written = helper.submit(write, t, rgb, mask, normals)
            written.result()
            frames.update()
        meta = {
            "cache_key": key,
            "generator_version": GENERATOR_VERSION,
            "config": asdict(config),
            "difficulty": preset,
            "fps": FPS,
            "head": f"procedural_head({HEAD_SEED}); also head.npz",
            "background": config.background,
            "light": asdict(LIGHTS[config.light]),
            "tracking_error": displacement,
            "triangles": renderer.triangle_count,
            "normals": "normals/*.png: OpenCV camera-space unit normals, see urhead.data.layout",
        }
        (writer.staging / "synthetic.json").write_text(json.dumps(meta, indent=1))
        write_manifest(writer.staging)
    return out


def scaled_head(head, factor: float):
    """``head`` with every length multiplied by ``factor`` (template and the shape, expression
    and pose blendshapes; the joints follow through the regressor)."""
    if factor == 1.0:
        return head
    return replace(
        head,
        v_template=head.v_template * factor,
        shapedirs=head.shapedirs * factor,
        posedirs=head.posedirs * factor,
    )


def _scaled_translation(viewmat: torch.Tensor, factor: float) -> torch.Tensor:
    scaled = viewmat.clone()
    scaled[:3, 3] *= factor
    return scaled


def _lbs(tables, betas, pose, transl):
    from urhead.ops import lbs

    out = lbs(
        betas.float().contiguous(),
        torch.from_numpy(pose[None]).contiguous(),
        transl=torch.from_numpy(transl[None]).contiguous(),
        **tables,
    )
    return out.verts[0].numpy(), out.rotations[0].numpy()


def face_displacement(head, tables, camera: Camera, exact, tracked, chunk: int = 64) -> dict:
    """What the tracking noise means in the image: the 2D displacement (pixels) of the face
    vertices between the head skinned with the ``exact`` and with the ``tracked``
    parameters, each (shape, expr (T, E), pose (T, 15), transl (T, 3)). Returns the mean
    over vertices and frames, the worst frame's mean and the largest, at the camera's
    resolution and scaled to 512² (displacements scale with the image side)."""
    face = head.region_vertices("face")
    frames = len(exact[1])
    per_frame_mean, per_frame_max = [], []
    for start in range(0, frames, chunk):
        span = slice(start, min(start + chunk, frames))
        uv_exact = _project_face(tables, camera, face, exact, span)
        uv_tracked = _project_face(tables, camera, face, tracked, span)
        distance = np.linalg.norm(uv_tracked - uv_exact, axis=-1)  # (frames, vertices)
        per_frame_mean.append(distance.mean(1))
        per_frame_max.append(distance.max(1))
    frame_mean, frame_max = np.concatenate(per_frame_mean), np.concatenate(per_frame_max)
    figures = {
        "mean_px": float(frame_mean.mean()),
        "worst_frame_mean_px": float(frame_mean.max()),
        "max_px": float(frame_max.max()),
    }
    to_512 = 512 / camera.width
    return {
        "what": "2D displacement of the face vertices, tracked vs exact parameters",
        "resolution": camera.width,
        **{name: round(v, 4) for name, v in figures.items()},
        **{f"{name}_at_512": round(v * to_512, 4) for name, v in figures.items()},
    }


def _project_face(tables, camera: Camera, face, params, span: slice) -> np.ndarray:
    """(frames, K, 2) pixel positions of the ``face`` vertices skinned with ``params``
    over the frames ``span``."""
    from urhead.ops import lbs

    shape, expr, pose, transl = params
    expr, pose, transl = (np.ascontiguousarray(a[span], np.float32) for a in (expr, pose, transl))
    betas = np.concatenate([np.broadcast_to(shape, (len(expr), len(shape))), expr], 1)
    out = lbs(
        torch.from_numpy(np.ascontiguousarray(betas, np.float32)),
        torch.from_numpy(pose),
        transl=torch.from_numpy(transl),
        **tables,
    )
    uv, _ = camera.project(out.verts[:, face])
    return uv.numpy()


class _Scene(NamedTuple):
    """One frame's triangles with their per-vertex attributes, ready to trace, and the
    BVH built over them when the frame starts a new tree."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    solid: np.ndarray
    face_material: np.ndarray
    bvh: TriangleBvh | None


class _FrameRenderer:
    """Per frame: subdivide and displace the skinned head, attach strands, ray-trace.

    The BVH is built every ``BVH_REBUILD_EVERY`` frames from that frame's mesh (with the
    mesh, so off the tracing thread) and refit in between (the topology never changes):
    frames rendered in order, frame t is traced with the tree of frame
    ``t - t % BVH_REBUILD_EVERY`` refit to frame t, whatever the timing."""

    BVH_REBUILD_EVERY = 25

    def __init__(self, look: SubjectLook, camera: Camera, config: SynthConfig):
        self.look = look
        self.camera = camera
        self.config = config
        self.light = LIGHTS[config.light]
        # A light without a directional part casts no shadows: skip the shadow rays.
        self.shadows = max(self.light.color) > 0
        self.eye = camera.center.double().numpy()
        self.triangle_count = 0
        self._bvh: TriangleBvh | None = None

    def scene(self, skinned, activation: dict, t: int) -> _Scene:
        verts, rotations = skinned
        look = self.look
        coarse = verts.astype(np.float64)
        fine = look.S @ coarse
        n0 = vertex_normals_numpy(fine, look.faces, look.normal_op)
        disp = look.static_offset.astype(np.float64).copy()
        for name, field in look.wrinkle_fields.items():
            disp += activation.get(name, 0.0) * field
        fine = fine + disp[:, None] * n0
        normals = vertex_normals_numpy(fine, look.faces, look.normal_op)
        parts = [(fine, look.faces, normals, look.colors, look.solid, look.face_material)]
        for strands in look.strands:
            if len(strands):
                parts.append(self._ribbons(strands, coarse, rotations))
        offset, pieces = 0, []
        for v, f, n, c, s, m in parts:
            pieces.append((v, f + offset, n, c, s, m))
            offset += len(v)
        arrays = [np.concatenate(x) for x in zip(*pieces, strict=True)]
        rebuild = t % self.BVH_REBUILD_EVERY == 0
        return _Scene(*arrays, bvh=TriangleBvh(arrays[0], arrays[1]) if rebuild else None)

    def render(self, scene: _Scene, t: int):
        """(rgb (H, W, 3), alpha (H, W), camera-space normals (H, W, 3)) of frame t; rgb
        is not clipped (highlights may exceed 1)."""
        if scene.bvh is not None:
            self._bvh = scene.bvh
        if self._bvh is None:
            raise RuntimeError("the first frame rendered must start a BVH")
        self.triangle_count = len(scene.faces)
        out = raytrace(
            scene.vertices,
            scene.faces,
            self.camera,
            normals=scene.normals,
            colors=scene.colors,
            solid=scene.solid,
            face_material=scene.face_material,
            materials=MATERIALS,
            decals=self.look.decals,
            light=self.light,
            shadows=self.shadows,
            samples_per_side=self.config.samples_per_side,
            edge_samples_per_side=self.config.edge_samples_per_side,
            background=self.config.background,
            seed=self.config.seed * 100003 + t,
            bvh=self._bvh,
            centre_hits=False,
        )
        # The tracer's normals are already zero where no sample hit.
        return out.rgb, out.alpha, out.normal

    def _ribbons(self, strands: Strands, coarse, rotations):
        """Camera-facing ribbons along each strand; the normals at the two edges lean
        sideways so the ribbon shades like a cylinder."""
        anchor = strands.anchor
        rot = rotations[anchor].astype(np.float64)  # (N, 3, 3)
        pts = coarse[anchor][:, None] + np.einsum(
            "nij,nkj->nki", rot, strands.offsets.astype(np.float64)
        )
        N, K, _ = pts.shape
        tangent = np.gradient(pts, axis=1)
        tangent /= np.maximum(np.linalg.norm(tangent, axis=2, keepdims=True), 1e-12)
        to_cam = self.eye - pts
        to_cam /= np.linalg.norm(to_cam, axis=2, keepdims=True)
        side = np.cross(tangent, to_cam)
        side /= np.maximum(np.linalg.norm(side, axis=2, keepdims=True), 1e-12)
        taper = np.linspace(1.0, 0.35, K)[None, :, None]
        half = 0.5 * strands.width[:, None, None] * taper
        verts = np.stack([pts - side * half, pts + side * half], 2).reshape(-1, 3)
        normals = np.stack([-0.75 * side + 0.66 * to_cam, 0.75 * side + 0.66 * to_cam], 2).reshape(
            -1, 3
        )
        base = (np.arange(N)[:, None] * K + np.arange(K - 1)[None]) * 2  # (N, K-1)
        a, b = base, base + 1
        a2, b2 = base + 2, base + 3
        faces = np.concatenate([np.stack([a, b, a2], -1), np.stack([b, b2, a2], -1)], 1).reshape(
            -1, 3
        )
        colors = np.repeat(strands.color, 2 * K, axis=0)
        rest_pts = (self.look.rest[anchor][:, None] + strands.offsets).astype(np.float64)
        solid = np.repeat(rest_pts, 2, axis=1).reshape(-1, 3)
        material = np.full(len(faces), strands.material, np.int32)
        return verts, faces.astype(np.int32), normals, colors, solid, material


def contact_sheet(
    root: str | Path, path: str | Path, columns: int = 6, rows: int = 3, tile: int = 256
) -> Path:
    """A grid of evenly spaced frames of the subject at ``root`` (timestep in the corner)."""
    from PIL import Image, ImageDraw

    from urhead.data import load_subject

    subject = load_subject(root, cache_size=1)
    # Index the frames without decoding them and read only the picked ones, one at a time
    # (every frame of a 600-frame subject decoded at once would hold ~5 GB).
    frames = [
        (r.timestep, split, i)
        for split in (subject.train, subject.test)
        for i, r in enumerate(split.records)
    ]
    frames.sort(key=lambda f: f[0])
    picks = np.linspace(0, len(frames) - 1, columns * rows).round().astype(int)
    sheet = Image.new("RGB", (columns * tile, rows * tile), "white")
    draw = ImageDraw.Draw(sheet)
    for i, k in enumerate(picks):
        _, split, index = frames[k]
        frame = split[index]
        image = Image.fromarray((frame.image.numpy() * 255).round().astype(np.uint8)).resize(
            (tile, tile), Image.LANCZOS
        )
        x, y = (i % columns) * tile, (i // columns) * tile
        sheet.paste(image, (x, y))
        draw.text((x + 6, y + 4), f"t={frame.timestep}", fill=(60, 60, 60))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "synth",
        help="make a synthetic ground-truth subject (ray-traced) in the VHAP layout",
        description="Render a synthetic subject from the built-in head with the ray tracer "
        "and write it in the VHAP / GaussianAvatars layout (reused when already there).",
    )
    defaults = SynthConfig()
    p.add_argument("--out", required=True, help="subject folder to write")
    p.add_argument("--frames", type=int, default=defaults.frames, help="number of frames (25 fps)")
    p.add_argument(
        "--resolution", type=int, default=defaults.resolution, help="image side in pixels"
    )
    p.add_argument(
        "--seed", type=int, default=defaults.seed, help="seed of identity, look and performance"
    )
    p.add_argument(
        "--difficulty",
        choices=list(DIFFICULTIES),
        default=defaults.difficulty,
        help="preset of performance, look and conditions (default %(default)s; hard is "
        "generator version 2's default)",
    )
    p.add_argument(
        "--light",
        choices=list(LIGHTS),
        help="key: small world-fixed key light; soft: large source, more ambient; "
        f"flat: even, no shading. Default: {_preset_values('light')}",
    )
    p.add_argument(
        "--hair",
        choices=list(HAIR_MODES),
        help="strands: volume + strands; shell: the volume as a surface; none: painted on "
        f"the scalp. Default: {_preset_values('hair')}",
    )
    p.add_argument(
        "--tracking-noise",
        type=float,
        help="scale of the noise on the exported FLAME parameters (0: exact). Default: "
        f"{_preset_values('tracking_noise')}",
    )
    p.add_argument(
        "--samples", type=int, default=defaults.samples_per_side, help="samples per pixel side"
    )
    p.add_argument(
        "--edge-samples",
        type=int,
        default=defaults.edge_samples_per_side,
        help="samples per pixel side at silhouettes, hair and occlusion edges",
    )
    p.add_argument(
        "--test-last", type=int, default=None, help="hold out the last N frames (default 30 %%)"
    )
    p.add_argument(
        "--background", default="white", help="background colour: white, black or R,G,B (0-255)"
    )
    p.add_argument(
        "--motion",
        choices=list(MOTIONS),
        default=defaults.motion,
        help="talking; extreme: ±90° yaw, ±45° pitch, jaw wide open, eyes at their limits; "
        "off_screen: the head half and wholly out of view (default %(default)s)",
    )
    p.add_argument(
        "--length-unit",
        type=float,
        default=defaults.length_unit,
        help="metres per length unit of the written files: 0.001 = millimetres "
        "(default %(default)s)",
    )
    p.add_argument("--contact-sheet", help="also write a grid of frames to this PNG")
    p.add_argument(
        "--force", action="store_true", help="replace an existing folder that is not a subject"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    before = _manifest_identity(Path(args.out))
    out = synthesize(args.out, config, progress=not args.quiet, force=args.force)
    # A subject made (again) is a new folder with a new manifest file.
    reused = before is not None and before == _manifest_identity(out)
    state = "reused (cached)" if reused else "wrote"
    size = f"{config.resolution}×{config.resolution}"
    print(
        f"{state} {out}: {config.frames} frames at {size}, difficulty {config.difficulty} "
        f"(light {config.light}, hair {config.hair}, tracking noise {config.tracking_noise:g})"
    )
    if args.contact_sheet:
        print(f"wrote {contact_sheet(out, args.contact_sheet)}")
    return 0


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """The resolved config of ``urhead synth`` arguments: given conditions override the
    difficulty's."""
    return SynthConfig(
        frames=args.frames,
        resolution=args.resolution,
        seed=args.seed,
        difficulty=args.difficulty,
        samples_per_side=args.samples,
        edge_samples_per_side=args.edge_samples,
        test_last=args.test_last,
        light=args.light,
        hair=args.hair,
        tracking_noise=args.tracking_noise,
        background=parse_background(args.background),
        motion=args.motion,
        length_unit=args.length_unit,
    ).resolved()


def _preset_values(condition: str) -> str:
    """'easy: key, default: soft, ...': a condition's value in each difficulty, for help."""
    return ", ".join(f"{name}: {preset[condition]}" for name, preset in DIFFICULTIES.items())


def _manifest_identity(out: Path) -> tuple[int, int] | None:
    try:
        stat = (out / MANIFEST).stat()
    except OSError:
        return None
    return stat.st_ino, stat.st_mtime_ns


def _key_at(out: Path):
    try:
        return json.loads((out / "synthetic.json").read_text()).get("cache_key")
    except (OSError, ValueError, AttributeError):  # unreadable, not JSON, not an object
        return None


__all__ = [
    "CONDITIONS",
    "DIFFICULTIES",
    "GENERATOR_VERSION",
    "LIGHTS",
    "SynthConfig",
    "config_from_args",
    "contact_sheet",
    "face_displacement",
    "subject_camera",
    "synthesize",
]
