"""Binary glTF 2.0 (``.glb``) files of one textured triangle mesh: positions, texture
coordinates and indices, the texture as an embedded PNG on an unlit material
(``KHR_materials_unlit``: the avatar's colour map is radiance with its shading baked in,
so a viewer's own lights must not shade it again; viewers without the extension show the
same texture on a rough, non-metallic PBR material).

glTF gives every vertex one texture coordinate, so mesh vertices on a UV seam are split
(:func:`seam_split`); glTF's texture origin is the image's top-left, so v is flipped from
the OBJ convention.
"""

from __future__ import annotations

import json
import struct

import numpy as np

from urhead.errors import ShapeError

_FLOAT, _UINT32 = 5126, 5125  # glTF componentType
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def seam_split(faces: np.ndarray, uv_faces: np.ndarray):
    """One glTF vertex per distinct (mesh vertex, UV vertex) pair of the face corners:
    ``(vertex_index, uv_index, triangles)`` — the first two (N,) say which mesh and UV
    vertex each glTF vertex copies, ``triangles`` (F, 3) indexes the glTF vertices."""
    if faces.shape != uv_faces.shape or faces.ndim != 2 or faces.shape[1] != 3:
        raise ShapeError(f"faces {faces.shape} and uv_faces {uv_faces.shape} must be (F, 3)")
    pairs = np.stack([faces.reshape(-1), uv_faces.reshape(-1)], 1).astype(np.int64)
    unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return unique[:, 0], unique[:, 1], inverse.reshape(-1, 3).astype(np.uint32)


def glb_bytes(
    positions: np.ndarray, texcoords: np.ndarray, triangles: np.ndarray, png: bytes
) -> bytes:
    """The GLB of (N, 3) positions, (N, 2) texture coordinates (OBJ convention, v up),
    (F, 3) triangles and a PNG texture."""
    positions = np.ascontiguousarray(positions, "<f4")
    texcoords = np.array(texcoords, "<f4")
    texcoords[:, 1] = 1.0 - texcoords[:, 1]  # glTF: v = 0 is the image's first row
    triangles = np.ascontiguousarray(triangles, "<u4")
    n = len(positions)
    if positions.shape != (n, 3) or texcoords.shape != (n, 2) or triangles.shape[1:] != (3,):
        raise ShapeError(
            f"positions {positions.shape}, texcoords {texcoords.shape}, triangles "
            f"{triangles.shape}: expected (N, 3), (N, 2), (F, 3)"
        )
    if triangles.size and int(triangles.max()) >= n:
        raise ShapeError(f"triangles index vertex {int(triangles.max())} of {n}")
    blobs = [positions.tobytes(), texcoords.tobytes(), triangles.tobytes(), png]
    views, offset = [], 0
    for blob in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += _padded(len(blob))
    views[0]["target"] = views[1]["target"] = _ARRAY_BUFFER
    views[2]["target"] = _ELEMENT_ARRAY_BUFFER
    document = {
        "asset": {"version": "2.0", "generator": "urhead"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "avatar"}],
        "meshes": [
            {
                "name": "avatar",
                "primitives": [
                    {
                        "attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                        "indices": 2,
                        "material": 0,
                        "mode": 4,
                    }
                ],
            }
        ],
        "materials": [
            {
                "name": "avatar",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": 0},
                    "metallicFactor": 0.0,
                    "roughnessFactor": 1.0,
                },
                "extensions": {"KHR_materials_unlit": {}},
            }
        ],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"bufferView": 3, "mimeType": "image/png"}],
        "accessors": [
            {
                "bufferView": 0,
                "componentType": _FLOAT,
                "count": n,
                "type": "VEC3",
                "min": positions.min(0).tolist(),
                "max": positions.max(0).tolist(),
            },
            {"bufferView": 1, "componentType": _FLOAT, "count": n, "type": "VEC2"},
            {
                "bufferView": 2,
                "componentType": _UINT32,
                "count": int(triangles.size),
                "type": "SCALAR",
            },
        ],
        "bufferViews": views,
        "buffers": [{"byteLength": offset}],
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (_padded(len(text)) - len(text))
    binary = b"".join(blob + b"\0" * (_padded(len(blob)) - len(blob)) for blob in blobs)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join(
        [
            struct.pack("<4sII", b"glTF", 2, total),
            struct.pack("<I4s", len(text), b"JSON"),
            text,
            struct.pack("<I4s", len(binary), b"BIN\0"),
            binary,
        ]
    )


def _padded(size: int) -> int:
    return (size + 3) // 4 * 4
