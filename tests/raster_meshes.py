"""Small deterministic meshes and cameras shared by the rasterizer tests."""

from __future__ import annotations

import math

import torch

import urhead


def uv_sphere(n_lat=8, n_lon=12, radius=1.0, jitter=0.0, seed=0, dtype=torch.float64):
    """A latitude-longitude sphere: welded geometry (V, 3) and (F, 3), plus a UV layout
    with a seam column (T, 2) and UV faces (F, 3), triangle-for-triangle."""
    verts, uvs = [], []
    for i in range(n_lat + 1):
        theta = math.pi * i / n_lat
        for j in range(n_lon):
            phi = 2 * math.pi * j / n_lon
            verts.append(
                [
                    radius * math.sin(theta) * math.cos(phi),
                    radius * math.cos(theta),
                    radius * math.sin(theta) * math.sin(phi),
                ]
            )
        for j in range(n_lon + 1):
            uvs.append([j / n_lon, 1 - i / n_lat])
    faces, uv_faces = [], []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
            c, d = (i + 1) * n_lon + j, (i + 1) * n_lon + (j + 1) % n_lon
            ua, ub = i * (n_lon + 1) + j, i * (n_lon + 1) + j + 1
            uc, ud = (i + 1) * (n_lon + 1) + j, (i + 1) * (n_lon + 1) + j + 1
            faces += [[a, c, b], [b, c, d]]
            uv_faces += [[ua, uc, ub], [ub, uc, ud]]
    v = torch.tensor(verts, dtype=torch.float64)
    if jitter:
        g = torch.Generator().manual_seed(seed)
        v = v + jitter * torch.randn(v.shape, generator=g, dtype=torch.float64)
    return (
        v.to(dtype),
        torch.tensor(faces, dtype=torch.int32),
        torch.tensor(uvs, dtype=dtype),
        torch.tensor(uv_faces, dtype=torch.int32),
    )


def camera(width=48, height=40, eye=(0.3, 0.2, -3.0), fov=45.0, near=0.01, far=100.0):
    return urhead.Camera.look_at(
        eye,
        (0.0, 0.0, 0.0),
        (0.0, -1.0, 0.0),
        fov_y_degrees=fov,
        width=width,
        height=height,
        near=near,
        far=far,
    )


def identity_camera(width, height, focal=100.0, cx=None, cy=None, near=0.01, far=1e5):
    """World = camera space: handy to place vertices at exact pixel positions."""
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    k = torch.tensor([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    return urhead.Camera(k, torch.eye(4), width, height, near, far)


def at_pixel(cam, x, y, depth, dtype=torch.float64):
    """Camera-space point (identity viewmat) that projects to pixel position (x, y)."""
    return torch.tensor(
        [(x - cam.cx) * depth / cam.fx, (y - cam.cy) * depth / cam.fy, depth], dtype=dtype
    )


def grid(n, alternate=True):
    """Faces of an n × n vertex grid (row-major vertex ids), quads split along alternating
    diagonals (checkerboard) so both diagonal directions occur. Returns faces (F, 3) and a
    colour class per face such that faces of one class share no vertex."""
    faces, classes = [], []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            flip = alternate and (i + j) % 2
            tris = [[a, b, d], [a, d, c]] if flip else [[a, b, c], [b, d, c]]
            for k, t in enumerate(tris):
                faces.append(t)
                classes.append((i % 2) * 4 + (j % 2) * 2 + k)
    return torch.tensor(faces, dtype=torch.int32), torch.tensor(classes)
