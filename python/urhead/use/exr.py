"""Writing EXR files through the OpenEXR package: ZIP-compressed scanline images of named
channels, 32-bit or (``half=True``) 16-bit floats. Channels of one layer are named
``layer.R``, ``layer.G``, … (the OpenEXR multi-layer convention readers such as Nuke,
Blender and OpenEXR's own group by); channels without a layer are ``Y`` or ``R G B(A)``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from urhead._atomic import c_library_path
from urhead.errors import InvalidArgumentError, ShapeError

_CHANNEL_NAMES = {1: "Y", 2: "RG", 3: "RGB", 4: "RGBA"}


def image_channels(image: np.ndarray, layer: str = "") -> dict[str, np.ndarray]:
    """An (H, W) or (H, W, C ≤ 4) image as named (H, W) channels: one channel ``Y``, two
    ``R G``, three ``R G B``, four ``R G B A``, each prefixed by ``layer.`` if given."""
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or not 1 <= a.shape[2] <= 4 or a.shape[0] == 0 or a.shape[1] == 0:
        raise ShapeError(f"image must be a non-empty (H, W) or (H, W, C ≤ 4), got {a.shape}")
    prefix = f"{layer}." if layer else ""
    return {prefix + c: a[..., i] for i, c in enumerate(_CHANNEL_NAMES[a.shape[2]])}


def write_exr(path: Path, channels: dict[str, np.ndarray], *, half: bool = False) -> None:
    """Writes named (H, W) float channels (all one size) to ``path``, ZIP-compressed."""
    import OpenEXR

    if not channels:
        raise InvalidArgumentError(f"{path}: an EXR needs at least one channel")
    dtype = np.float16 if half else np.float32
    planes = {name: np.ascontiguousarray(a, dtype=dtype) for name, a in channels.items()}
    shape = next(iter(planes.values())).shape
    for name, plane in planes.items():
        if plane.ndim != 2 or plane.shape != shape:
            raise ShapeError(f"{path}: channel {name!r} is {plane.shape}, expected {shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, planes) as f, c_library_path(path, "w") as name:
        f.write(name)
