"""``urhead export AVATAR``: per-frame 3DGS PLY files, textured OBJ meshes and the UV maps.

- ``--ply DIR``: ``DIR/{timestep:05d}.ply`` per frame in world space (:mod:`urhead.use.ply`):
  the Gaussian layer, then the mesh as flat opaque surface Gaussians
  (:mod:`urhead.use.ply_layers`; ``--gaussians-only`` leaves them out). The avatar
  evaluates SH colours in each sample's rest frame; the export rotates the coefficients
  into the world frame (:mod:`urhead.use.sh_rotation`) with the nearest proper rotation to
  the blended skinning rotation. Where a face's vertices share one joint rotation
  (everywhere but the blend seams of neck, jaw and eyes) that rotation is exact, so
  ``--gaussians-only`` renders the avatar's Gaussian layer.
- ``--mesh DIR``: ``DIR/{timestep:05d}.obj`` per frame (displaced posed mesh with the
  FLAME UV layout), one ``material.mtl`` and ``texture.png`` (the colour map's DC term).
- ``--glb DIR``: ``DIR/{timestep:05d}.glb`` per frame, binary glTF of the same mesh with
  the DC colour map embedded as an unlit texture (:mod:`urhead.use.glb`).
- ``--maps DIR``: every UV map as ZIP-compressed float EXR (``--half``: 16-bit floats):
  ``color.exr`` with one layer per SH coefficient (``sh00.R`` … ``shKK.B``),
  ``normal.exr``, ``displacement.exr``, ``opacity.exr`` logits, ``scale.exr`` log
  standard deviations; plus PNG previews, image row 0 at v = 1.

``--frames`` takes any timestep of the avatar or of its subject: held-out timesteps are
posed with their tracked FLAME parameters, as ``urhead render --orbit`` does.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from urhead._atomic import write_directory_atomically
from urhead._progress import tracked
from urhead.data.images import write_bgr_png
from urhead.model import Avatar
from urhead.sh import SH_C0
from urhead.use.common import (
    OpenedAvatar,
    check_output_dir,
    frame_at,
    open_avatar,
    open_subject,
    parse_timesteps,
    selectable_timesteps,
)
from urhead.use.exr import image_channels, write_exr
from urhead.use.glb import glb_bytes, seam_split
from urhead.use.ply import write_gaussian_ply
from urhead.use.ply_layers import DEFAULT_SPACING_PIXELS, mesh_surfels, world_gaussians


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "export",
        help="export an avatar as 3DGS PLY files, textured meshes or UV maps",
        description="Export a fitted avatar: per-frame standard 3DGS PLY files in world "
        "space holding the Gaussians and the mesh as surface Gaussians (--ply), "
        "per-frame textured OBJ meshes (--mesh) and binary glTF (--glb), "
        "the UV maps as compressed "
        "float EXR with PNG previews (--maps). Each output folder is written whole, then renamed "
        "into place (an existing one is replaced).",
    )
    p.add_argument("avatar", type=Path, help="avatar directory (the fit's OUT/avatar)")
    p.add_argument("--ply", type=Path, default=None, metavar="DIR", help="write PLY files here")
    p.add_argument("--mesh", type=Path, default=None, metavar="DIR", help="write OBJ files here")
    p.add_argument(
        "--glb", type=Path, default=None, metavar="DIR", help="write textured GLB files here"
    )
    p.add_argument("--maps", type=Path, default=None, metavar="DIR", help="write UV maps here")
    p.add_argument(
        "--frames",
        default=None,
        help="timesteps to export, e.g. '0,5,10-20': frames of the avatar or, held out, of "
        "its subject (default: every frame of the avatar)",
    )
    p.add_argument(
        "--gaussians-only",
        action="store_true",
        help="--ply: the Gaussian layer alone, without the mesh as surface Gaussians (a "
        "viewer then sees through the head where the avatar shows its mesh)",
    )
    p.add_argument(
        "--surfel-spacing",
        type=float,
        default=DEFAULT_SPACING_PIXELS,
        metavar="PX",
        help="--ply: spacing of the mesh's surface Gaussians in pixels of the avatar's camera "
        "(smaller: closer to the avatar, larger files)",
    )
    p.add_argument(
        "--half", action="store_true", help="--maps: 16-bit half floats instead of 32-bit"
    )
    p.add_argument(
        "--subject",
        type=Path,
        default=None,
        help="subject folder (default: the fit's); needed only for held-out --frames and "
        "for avatars that record no camera",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    outputs = {"--ply": args.ply, "--mesh": args.mesh, "--glb": args.glb, "--maps": args.maps}
    if all(path is None for path in outputs.values()):
        raise ValueError("nothing to export: pass --ply, --mesh, --glb and/or --maps DIR")
    for option, path in outputs.items():
        if path is not None:
            check_output_dir(path, option)
    opened = open_avatar(args.avatar)
    avatar = opened.avatar
    if args.gaussians_only and args.ply is None:
        raise ValueError("--gaussians-only applies to --ply; pass --ply DIR")
    if args.gaussians_only and avatar.num_gaussians == 0:
        raise ValueError(
            f"--gaussians-only: the avatar {args.avatar} has no Gaussians (a mesh-only fit)"
        )
    if not args.surfel_spacing > 0:
        raise ValueError(f"--surfel-spacing must be > 0 pixels, got {args.surfel_spacing}")
    subject = None
    if any(path is not None for path in (args.ply, args.mesh, args.glb)):
        subject = open_subject(opened, args.subject, required=False)
    timesteps = parse_timesteps(
        args.frames, selectable_timesteps(opened, subject), default=avatar.timesteps.tolist()
    )
    with torch.no_grad():
        if args.ply is not None:
            write_directory_atomically(
                args.ply,
                lambda tmp: write_ply_frames(
                    opened,
                    subject,
                    timesteps,
                    tmp,
                    gaussians_only=args.gaussians_only,
                    spacing_pixels=args.surfel_spacing,
                ),
            )
            print(f"wrote {len(timesteps)} PLY files to {args.ply}")
        if args.mesh is not None:
            write_directory_atomically(
                args.mesh, lambda tmp: write_mesh_frames(opened, subject, timesteps, tmp)
            )
            print(f"wrote {len(timesteps)} OBJ meshes to {args.mesh}")
        if args.glb is not None:
            write_directory_atomically(
                args.glb, lambda tmp: write_glb_frames(opened, subject, timesteps, tmp)
            )
            print(f"wrote {len(timesteps)} GLB files to {args.glb}")
        if args.maps is not None:
            write_directory_atomically(args.maps, lambda tmp: write_maps(opened, tmp, args.half))
            print(f"wrote the UV maps to {args.maps}")
    return 0


def write_ply_frames(
    opened: OpenedAvatar,
    subject,
    timesteps: list[int],
    folder: Path,
    *,
    gaussians_only: bool = False,
    spacing_pixels: float = DEFAULT_SPACING_PIXELS,
) -> None:
    avatar = opened.avatar
    for t in tracked(timesteps, len(timesteps), "export --ply"):
        params, camera = frame_at(opened, subject, t)
        layers = []
        if avatar.num_gaussians > 0:
            layers.append(world_gaussians(avatar, params, camera))
        if not gaussians_only:
            layers.append(mesh_surfels(avatar, params, camera, spacing_pixels))
        arrays = {key: torch.cat([layer[key] for layer in layers]) for key in layers[0]}
        write_gaussian_ply(folder / f"{t:05d}.ply", **arrays)


def dc_texture(avatar: Avatar) -> np.ndarray:
    """(R, R, 3) float RGB in [0, 1]: the colour map's view-independent (DC) term."""
    dc = avatar.maps.detach()[..., 0:3]
    return (dc * SH_C0 + 0.5).clamp(0, 1).numpy()


def write_mesh_frames(opened: OpenedAvatar, subject, timesteps: list[int], folder: Path) -> None:
    avatar = opened.avatar
    head = avatar.head
    rgb = (dc_texture(avatar) * 255 + 0.5).astype(np.uint8)
    write_bgr_png(folder / "texture.png", rgb[..., ::-1])
    (folder / "material.mtl").write_text(
        "newmtl avatar\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd texture.png\n"
    )
    vt = "".join(f"vt {u:.6f} {v:.6f}\n" for u, v in head.uv_coords)
    corners = np.stack([head.faces + 1, head.uv_faces + 1], -1).reshape(-1, 6)
    faces = "".join("f {}/{} {}/{} {}/{}\n".format(*row) for row in corners.tolist())
    for t in tracked(timesteps, len(timesteps), "export --mesh"):
        verts = posed_vertices(opened, subject, t)
        v = "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in verts.tolist())
        text = f"# urhead avatar, timestep {t}\nmtllib material.mtl\n{v}{vt}usemtl avatar\n{faces}"
        (folder / f"{t:05d}.obj").write_text(text)


def posed_vertices(opened: OpenedAvatar, subject, timestep: int) -> torch.Tensor:
    """(V, 3) the displaced posed mesh of ``timestep`` in world space."""
    params, camera = frame_at(opened, subject, timestep)
    return opened.avatar.render(params, camera, gaussians=False).mesh.verts


def write_glb_frames(opened: OpenedAvatar, subject, timesteps: list[int], folder: Path) -> None:
    import cv2

    head = opened.avatar.head
    rgb = (dc_texture(opened.avatar) * 255 + 0.5).astype(np.uint8)
    ok, png = cv2.imencode(".png", rgb[..., ::-1])
    if not ok:
        raise OSError(f"{folder}: cannot encode the texture as PNG")
    vertex_index, uv_index, triangles = seam_split(head.faces, head.uv_faces)
    texcoords = head.uv_coords[uv_index]
    for t in tracked(timesteps, len(timesteps), "export --glb"):
        verts = posed_vertices(opened, subject, t).numpy()
        data = glb_bytes(verts[vertex_index], texcoords, triangles, png.tobytes())
        (folder / f"{t:05d}.glb").write_bytes(data)


def write_maps(opened: OpenedAvatar, folder: Path, half: bool = False) -> None:
    avatar = opened.avatar
    layout = avatar.layout
    maps = avatar.maps.detach().numpy()
    coeffs = maps[..., layout.color].reshape(*maps.shape[:2], layout.sh_coeffs, 3)
    color = {}
    for k in range(layout.sh_coeffs):
        color.update(image_channels(coeffs[:, :, k], layer=f"sh{k:02d}"))
    files = {"color.exr": color}
    files["normal.exr"] = image_channels(maps[..., layout.normal])
    files["displacement.exr"] = image_channels(maps[..., layout.displacement])
    previews = {
        "color.png": dc_texture(avatar),
        "normal.png": 0.5 + 0.5 * _unit(maps[..., layout.normal]),
        "displacement.png": _stretch(maps[..., layout.displacement]),
    }
    if layout.gaussians:
        files["opacity.exr"] = image_channels(maps[..., layout.opacity])
        files["scale.exr"] = image_channels(maps[..., layout.scale])
        previews["opacity.png"] = 1 / (1 + np.exp(-maps[..., layout.opacity]))
        previews["scale.png"] = _stretch(maps[..., layout.scale].mean(-1))
    for name, channels in files.items():
        write_exr(folder / name, channels, half=half)
    for name, image in previews.items():
        pixels = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
        if pixels.ndim == 3:
            pixels = pixels[..., ::-1]
        write_bgr_png(folder / name, pixels)
    description = {
        "orientation": "image row 0 is v = 1 (OBJ texture convention)",
        "color.exr": "layer shKK (channels shKK.R, .G, .B): SH coefficient k (3DGS basis, "
        "rest-frame view direction)",
        "pixel_type": "half" if half else "float",
        "normal.exr": "rest-pose normal xyz (not normalised)",
        "displacement.exr": "displacement along the posed normal, metres (channel Y)",
        "opacity.exr": "opacity logit (channel Y)",
        "scale.exr": "log standard deviations, the third along the normal (RGB = 1, 2, 3)",
        "previews": "color.png DC colour, normal.png 0.5 + 0.5·n, displacement.png and "
        "scale.png min–max stretched, opacity.png sigmoid",
        "sh_degree": layout.sh_degree,
    }
    (folder / "maps.json").write_text(json.dumps(description, indent=2))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _stretch(v: np.ndarray) -> np.ndarray:
    lo, hi = float(v.min()), float(v.max())
    return (v - lo) / (hi - lo) if hi > lo else np.zeros_like(v)
