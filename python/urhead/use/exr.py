"""A minimal OpenEXR writer: single-part scanline images, uncompressed, 32-bit float
channels. The OpenCV wheels ship without OpenEXR, and float maps need no more than this.

Layout (OpenEXR file-layout spec): magic 20000630, version 2, a header of attributes
(``channels``, ``compression``, ``dataWindow``, ``displayWindow``, ``lineOrder``,
``pixelAspectRatio``, ``screenWindowCenter``, ``screenWindowWidth``) ended by a null byte,
a table of scanline offsets, then per scanline: y, byte count, and each channel's row
(channels in alphabetical order, as the format requires).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from urhead.errors import InvalidArgumentError, ShapeError

_FLOAT = 2  # pixel type FLOAT


def _attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def exr_bytes(channels: dict[str, np.ndarray]) -> bytes:
    """The EXR file of named (H, W) float channels (e.g. ``{"R": r, "G": g, "B": b}``)."""
    if not channels:
        raise InvalidArgumentError("channels must name at least one channel")
    names = sorted(channels)
    planes = [np.asarray(channels[c], dtype="<f4") for c in names]
    h, w = planes[0].shape if planes[0].ndim == 2 else (None, None)
    for c, p in zip(names, planes, strict=True):
        if p.ndim != 2 or p.shape != (h, w) or h == 0 or w == 0:
            raise ShapeError(f"channel {c!r} must be a non-empty (H, W) array like the others")
        if not c or "\0" in c:
            raise InvalidArgumentError(f"channel name {c!r} is invalid")
    chlist = (
        b"".join(c.encode() + b"\0" + struct.pack("<iB3xii", _FLOAT, 0, 1, 1) for c in names)
        + b"\0"
    )
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    header = b"".join(
        [
            struct.pack("<ii", 20000630, 2),
            _attribute("channels", "chlist", chlist),
            _attribute("compression", "compression", b"\0"),
            _attribute("dataWindow", "box2i", box),
            _attribute("displayWindow", "box2i", box),
            _attribute("lineOrder", "lineOrder", b"\0"),
            _attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
            _attribute("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
            _attribute("screenWindowWidth", "float", struct.pack("<f", 1.0)),
            b"\0",
        ]
    )
    row_bytes = 4 * w * len(names)
    block = 8 + row_bytes
    start = len(header) + 8 * h
    offsets = np.arange(h, dtype="<u8") * block + start
    rows = np.stack(planes, 1).reshape(h, row_bytes // 4)  # (H, C·W): channel rows per line
    lines = np.empty((h, block), np.uint8)
    lines[:, :4] = np.arange(h, dtype="<i4")[:, None].view(np.uint8)
    lines[:, 4:8] = np.full((h, 1), row_bytes, "<i4").view(np.uint8)
    lines[:, 8:] = rows.view(np.uint8)
    return header + offsets.tobytes() + lines.tobytes()


def write_exr(path: Path, image: np.ndarray) -> None:
    """Writes an (H, W) or (H, W, C ≤ 4) float image: one channel as ``Y``, three as
    ``R G B``, four as ``R G B A``, two as ``R G``."""
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        channels = {"Y": a}
    elif a.ndim == 3 and 1 <= a.shape[2] <= 4:
        names = {1: "Y", 2: "RG", 3: "RGB", 4: "RGBA"}[a.shape[2]]
        channels = {c: a[..., i] for i, c in enumerate(names)}
    else:
        raise ShapeError(f"image must be (H, W) or (H, W, C ≤ 4), got {a.shape}")
    Path(path).write_bytes(exr_bytes(channels))
