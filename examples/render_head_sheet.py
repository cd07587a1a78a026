"""Render the built-in procedural head: a turntable and an expression sheet for the README.

    python examples/render_head_sheet.py [--out docs/images] [--size 320]

A small z-buffer rasterizer in numpy (back-face culled, per-pixel interpolated normals and
colours, a key light, a fill light and a rim light) so the images need nothing but the
head model; the project's own differentiable rasterizer lives in ``urhead.ops``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from urhead.head import REGION_NAMES, procedural_head
from urhead.head.mesh import vertex_normals_numpy

SKIN = np.array([0.86, 0.66, 0.55])
COLOURS = {
    "face": SKIN,
    "scalp": np.array([0.32, 0.22, 0.16]),
    "neck": SKIN * 0.97,
    "ears": SKIN * 0.98,
    "eyes": np.array([0.93, 0.92, 0.90]),
    "lips": np.array([0.72, 0.40, 0.38]),
    "mouth_interior": np.array([0.36, 0.10, 0.10]),
    "teeth": np.array([0.93, 0.91, 0.84]),
}


def vertex_colours(head) -> np.ndarray:
    """(V, 3) albedo by region; irises and pupils painted on the eyeballs."""
    colours = np.stack([COLOURS[name] for name in REGION_NAMES])[head.vertex_region]
    joints = head.j_regressor @ head.v_template
    for eye_joint, region_value in ((3, 1), (4, -1)):
        ids = head.region_vertices("eyes")
        ids = ids[np.sign(head.v_template[ids, 0]) == region_value]
        d = head.v_template[ids] - joints[eye_joint]
        cos = d[:, 2] / np.linalg.norm(d, axis=1)
        iris = np.array([0.30, 0.42, 0.55])
        colours[ids] = np.where((cos > 0.88)[:, None], iris, colours[ids])
        colours[ids] = np.where((cos > 0.975)[:, None], 0.05, colours[ids])
    return _soften(colours, head.faces, head.vertex_region != REGION_NAMES.index("eyes"))


def _soften(colours, faces, movable, rounds=3):
    """Blend colours with their mesh neighbours so region borders are not stair-stepped."""
    for _ in range(rounds):
        total = np.zeros_like(colours)
        count = np.zeros(len(colours))
        for k in range(3):
            for j in range(3):
                np.add.at(total, faces[:, k], colours[faces[:, j]])
                np.add.at(count, faces[:, k], 1)
        colours = np.where(movable[:, None], total / np.maximum(count, 1)[:, None], colours)
    return colours


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World→camera (OpenCV axes: x right, y down, z forward)."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    view = np.eye(4)
    view[:3, :3] = np.stack([x, y, z])
    view[:3, 3] = -view[:3, :3] @ eye
    return view


def render(verts, faces, colours, view, focal, size, background=1.0) -> np.ndarray:
    """(size, size, 3) float image of the mesh seen by a pinhole camera."""
    normals = vertex_normals_numpy(verts, faces)
    cam = verts @ view[:3, :3].T + view[:3, 3]
    n_cam = normals @ view[:3, :3].T
    px = focal * cam[:, :2] / cam[:, 2:3] + size / 2
    image = np.full((size, size, 3), background, np.float64)
    depth = np.full((size, size), np.inf)
    tri = px[faces]
    signed = (tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1]) - (
        tri[:, 2, 0] - tri[:, 0, 0]
    ) * (tri[:, 1, 1] - tri[:, 0, 1])
    visible = np.flatnonzero((signed < -1e-9) & np.all(cam[faces][:, :, 2] > 0.01, axis=1))
    key = np.array([-0.5, -0.6, -0.62])
    key /= np.linalg.norm(key)
    fill = np.array([0.7, -0.1, -0.7])
    fill /= np.linalg.norm(fill)
    for f in visible:
        t = tri[f]
        x0, y0 = np.floor(t.min(0)).astype(int)
        x1, y1 = np.ceil(t.max(0)).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, size - 1), min(y1, size - 1)
        if x1 < x0 or y1 < y0:
            continue
        xs, ys = np.meshgrid(np.arange(x0, x1 + 1) + 0.5, np.arange(y0, y1 + 1) + 0.5)
        a, b, c = t
        w1 = ((xs - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (ys - a[1])) / signed[f]
        w2 = ((b[0] - a[0]) * (ys - a[1]) - (xs - a[0]) * (b[1] - a[1])) / signed[f]
        w0 = 1 - w1 - w2
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        if not inside.any():
            continue
        ids = faces[f]
        z = w0 * cam[ids[0], 2] + w1 * cam[ids[1], 2] + w2 * cam[ids[2], 2]
        rows, cols = ys.astype(int), xs.astype(int)
        closer = inside & (z < depth[rows, cols])
        if not closer.any():
            continue
        r, cc, wz = rows[closer], cols[closer], z[closer]
        w = np.stack([w0[closer], w1[closer], w2[closer]], 1)
        n = w @ n_cam[ids]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        albedo = w @ colours[ids]
        view_dir = -(w @ cam[ids])
        view_dir /= np.linalg.norm(view_dir, axis=1, keepdims=True)
        diffuse = 0.78 * np.clip(n @ key, 0, None) + 0.28 * np.clip(n @ fill, 0, None)
        rim = 0.25 * np.clip(1 - np.abs((n * view_dir).sum(1)), 0, 1) ** 3
        half = key + view_dir
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        spec = 0.12 * np.clip((n * half).sum(1), 0, 1) ** 40
        shade = 0.2 + diffuse
        image[r, cc] = np.clip(albedo * shade[:, None] + (spec + rim)[:, None], 0, 1)
        depth[r, cc] = wz
    return image


def posed(head, expr=None, pose=None) -> np.ndarray:
    e = torch.zeros(1, head.num_expr, dtype=torch.float64)
    p = torch.zeros(1, 15, dtype=torch.float64)
    for k, v in (expr or {}).items():
        e[0, k] = v
    for k, v in (pose or {}).items():
        p[0, k] = v
    return head.skin(expr=e, pose=p).verts[0].numpy()


def view_around(angle_deg, distance=0.62, height=0.02):
    a = np.deg2rad(angle_deg)
    target = np.array([0.0, 0.0, 0.0])
    eye = target + np.array([distance * np.sin(a), height, distance * np.cos(a)])
    return look_at(eye, target)


def labelled(image: np.ndarray, text: str) -> Image.Image:
    im = Image.fromarray((image * 255).astype(np.uint8))
    ImageDraw.Draw(im).text((8, 6), text, fill=(40, 40, 40))
    return im


def sheet(images: list[Image.Image], columns: int) -> Image.Image:
    w, h = images[0].size
    rows = (len(images) + columns - 1) // columns
    out = Image.new("RGB", (w * columns, h * rows), (255, 255, 255))
    for k, im in enumerate(images):
        out.paste(im, ((k % columns) * w, (k // columns) * h))
    return out


EXPRESSIONS = [
    ("neutral", {}, {}),
    ("jaw open", {}, {6: 0.35}),
    ("smile", {0: 1.0}, {}),
    ("brow raise", {1: 1.0}, {}),
    ("blink", {2: 1.0}, {}),
    ("pucker", {3: 1.0}, {}),
    ("eye gaze", {}, {9: 0.0, 10: 0.45, 12: 0.0, 13: 0.45}),
    ("neck turn", {}, {4: 0.5}),
]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/images")
    parser.add_argument("--size", type=int, default=320)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    head = procedural_head()
    colours = vertex_colours(head)
    focal = args.size * 2.3
    rest = posed(head)
    turn = [
        labelled(render(rest, head.faces, colours, view_around(a), focal, args.size), f"{a}°")
        for a in range(0, 360, 45)
    ]
    sheet(turn, 4).save(out / "head_turntable.png")
    faces = []
    for name, expr, pose in EXPRESSIONS:
        verts = posed(head, expr, pose)
        faces.append(
            labelled(render(verts, head.faces, colours, view_around(20), focal, args.size), name)
        )
    sheet(faces, 4).save(out / "head_expressions.png")
    print(f"wrote {out / 'head_turntable.png'} and {out / 'head_expressions.png'}")


if __name__ == "__main__":
    main()
