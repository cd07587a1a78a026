"""Subjects laid out exactly as VHAP's exporter writes them (FORMATS.md, "How VHAP's exporter
writes the split files"), built here from those rules and independently of urhead's
``SubjectWriter``:

- frames timestep-major, camera-minor, each with its own intrinsics and OpenGL
  camera-to-world; the top-level intrinsics are the last frame's;
- ``transforms.json``, ``transforms_backup.json`` (written before the FLAME parameters: no
  ``flame_param_path``) and ``transforms_backup_flame.json`` list everything;
- the first ceil(0.7·T) timesteps train, the rest test; one camera: ``val`` has no frames
  and no cameras but lists the training timesteps; several cameras: camera 8 (else the
  last) is ``val`` over the training timesteps, train has the others, test every camera;
- images composited on white or black, soft foreground masks, FLAME parameters as float32
  npz per timestep, ``canonical_flame_param.npz`` with VHAP's float64 jaw.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from urhead import Camera

W, H = 40, 32
BACKGROUNDS = {"white": 255, "black": 0}


def vhap_camera(index: int) -> Camera:
    """Camera ``index`` on an arc 0.8 m from the origin, looking at it, each with its own
    focal lengths and principal point."""
    angle = math.radians(-20.0 + 20.0 * index)
    eye = (0.8 * math.sin(angle), 0.02, 0.8 * math.cos(angle))
    cam = Camera.look_at(eye, (0.0, 0.0, 0.0), width=W, height=H)
    k = torch.tensor(
        [[60.0 + index, 0, W / 2 + 0.5 * index], [0, 61.0 + index, H / 2 - 1], [0, 0, 1]]
    )
    return Camera(k, cam.viewmat, W, H)


def _frame_entry(t: int, c: int, camera: Camera) -> dict:
    fx, fy = float(camera.K[0, 0]), float(camera.K[1, 1])
    c2w = np.linalg.inv(camera.viewmat.double().numpy())
    c2w[:3, 1:3] *= -1  # OpenCV → OpenGL camera axes
    return {
        "timestep_index": t,
        "timestep_index_original": t,
        "timestep_id": f"{t:05d}",
        "camera_index": c,
        "camera_id": f"22{c:07d}",
        "cx": float(camera.K[0, 2]),
        "cy": float(camera.K[1, 2]),
        "fl_x": fx,
        "fl_y": fy,
        "h": H,
        "w": W,
        "camera_angle_x": 2 * math.atan(W / (2 * fx)),
        "camera_angle_y": 2 * math.atan(H / (2 * fy)),
        "transform_matrix": c2w.tolist(),
        "file_path": f"images/{t:05d}_{c:02d}.png",
        "fg_mask_path": f"fg_masks/{t:05d}_{c:02d}.png",
        "flame_param_path": f"flame_param/{t:05d}.npz",
    }


def _flame(rng, t: int, num_vertices: int | None) -> dict:
    small = lambda n: (0.02 * rng.normal(size=(1, n))).astype(np.float32)  # noqa: E731
    params = {
        "translation": small(3),
        "rotation": small(3),
        "neck_pose": small(3),
        "jaw_pose": small(3),
        "eyes_pose": small(6),
        "shape": np.zeros(300, np.float32),
        "expr": small(100),
    }
    if num_vertices is not None:
        params["static_offset"] = np.full((1, num_vertices, 3), 1e-4, np.float32)
        params["dynamic_offset"] = np.full((1, num_vertices, 3), 1e-5 * t, np.float32)
    return params


def _write_images(root: Path, entry: dict, rng, background: int) -> None:
    yy, xx = np.mgrid[0:H, 0:W]
    dist = np.hypot((xx - W / 2) / (0.3 * W), (yy - H / 2) / (0.35 * H))
    alpha = np.clip((1.2 - dist) / 0.4, 0, 1)  # soft edge, exactly 0 outside
    fg = rng.integers(60, 200, size=(H, W, 3)).astype(np.float64)
    image = alpha[..., None] * fg + (1 - alpha[..., None]) * background
    cv2.imwrite(str(root / entry["file_path"]), np.rint(image).astype(np.uint8)[..., ::-1])
    cv2.imwrite(str(root / entry["fg_mask_path"]), np.rint(alpha * 255).astype(np.uint8))


def _split(db: dict, train_ratio: float = 0.7) -> dict[str, dict]:
    shared = {
        k: v for k, v in db.items() if k not in ("frames", "timestep_indices", "camera_indices")
    }
    timesteps, cameras = sorted(db["timestep_indices"]), db["camera_indices"]
    nt_train = math.ceil(len(timesteps) * train_ratio)
    lists = {
        "train": timesteps[:nt_train],
        "val": timesteps[:nt_train],  # val shares the training timesteps
        "test": timesteps[nt_train:],
    }
    if len(cameras) > 1:
        held = 8 if 8 in cameras else cameras[-1]
        cams = {"train": [c for c in cameras if c != held], "val": [held], "test": cameras}
    else:
        cams = {"train": cameras, "val": [], "test": cameras}
    out = {name: {**shared, "frames": []} for name in ("train", "val", "test")}
    for name in out:
        out[name]["timestep_indices"] = lists[name]
        out[name]["camera_indices"] = cams[name]
    for f in db["frames"]:
        t, c = f["timestep_index"], f["camera_index"]
        if t in lists["train"]:
            out["train" if c in cams["train"] else "val"]["frames"].append(f)
        else:
            out["test"]["frames"].append(f)
    return out


def write_vhap_export(
    root,
    num_timesteps: int = 7,
    cameras: tuple[int, ...] = (0,),
    background: str = "white",
    num_vertices: int | None = 5143,
    seed: int = 0,
) -> Path:
    """A subject at ``root`` as VHAP's exporter writes it, for the camera indices
    ``cameras`` (one: monocular). ``num_vertices``: the size of ``static_offset`` and
    ``dynamic_offset`` (None: no offsets)."""
    root = Path(root)
    for sub in ("images", "fg_masks", "flame_param"):
        (root / sub).mkdir(parents=True)
    rng = np.random.default_rng(seed)
    frames = []
    for t in range(num_timesteps):
        np.savez(root / f"flame_param/{t:05d}.npz", **_flame(rng, t, num_vertices))
        for c in cameras:
            entry = _frame_entry(t, c, vhap_camera(c))
            _write_images(root, entry, rng, BACKGROUNDS[background])
            frames.append(entry)
    last = frames[-1]
    intrinsics = ("cx", "cy", "fl_x", "fl_y", "h", "w", "camera_angle_x", "camera_angle_y")
    db = {
        "frames": frames,
        **{k: last[k] for k in intrinsics},
        "timestep_indices": list(range(num_timesteps)),
        "camera_indices": sorted(cameras),
    }
    canonical = {k: np.zeros_like(v) for k, v in _flame(rng, 0, num_vertices).items()}
    canonical["jaw_pose"] = np.array([[0.3, 0, 0]])  # float64, as VHAP writes it
    canonical.pop("dynamic_offset", None)
    np.savez(root / "canonical_flame_param.npz", **canonical)
    before_flame = [{k: v for k, v in f.items() if k != "flame_param_path"} for f in frames]
    files = {
        "transforms.json": db,
        "transforms_backup.json": {**db, "frames": before_flame},
        "transforms_backup_flame.json": db,
        **{f"transforms_{name}.json": meta for name, meta in _split(db).items()},
    }
    for name, meta in files.items():
        (root / name).write_text(json.dumps(meta, indent=4))
    return root
