"""PNG (and EXR normal map) reading and writing for datasets: a cheap header check used
at load time, and decoding that names the file on any failure."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from urhead._atomic import c_library_path, write_bytes
from urhead.data.layout import DatasetError, MissingFileError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # PNG colour type → channels after decoding


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from the PNG header (33 bytes read), or a :class:`DatasetError`."""
    try:
        with open(path, "rb") as f:
            head = f.read(33)
    except FileNotFoundError:
        raise MissingFileError(path, "file not found") from None
    except OSError as e:
        raise DatasetError(path, f"cannot be read ({e})") from None
    if len(head) < 33 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise DatasetError(path, "not a PNG file (bad signature or header)")
    width, height = struct.unpack(">II", head[16:24])
    if width == 0 or height == 0:
        raise DatasetError(path, f"PNG header gives an empty image {width}×{height}")
    return width, height


def decode_image(path: Path) -> np.ndarray:
    """The image file at ``path`` decoded by OpenCV as stored (BGR(A) order, uint8 or
    uint16). The bytes are read by Python, so any path works, valid UTF-8 or not."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise MissingFileError(path, "file not found") from None
    except OSError as e:
        raise DatasetError(path, f"cannot be read ({e.strerror})") from None
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if raw is None:
        raise DatasetError(path, "could not be decoded as an image (corrupt or truncated?)")
    return raw


def check_png(path: Path, width: int, height: int, channels: tuple[int, ...]) -> None:
    """Decodes the PNG at ``path`` whole and checks its size, bit depth (8 or 16) and
    channel count; a :class:`DatasetError` naming the file otherwise."""
    raw = decode_image(path)
    found = 1 if raw.ndim == 2 else raw.shape[2]
    if raw.dtype not in (np.uint8, np.uint16):
        raise DatasetError(path, f"unsupported pixel type {raw.dtype} (8 or 16 bits per channel)")
    if raw.shape[:2] != (height, width):
        raise DatasetError(path, f"decodes to {raw.shape[1]}×{raw.shape[0]}, not {width}×{height}")
    if found not in channels:
        raise DatasetError(
            path, f"has {found} channels, expected {' or '.join(map(str, channels))}"
        )


def read_png(path: Path) -> np.ndarray:
    """Decoded PNG as (H, W) or (H, W, C) with RGB(A) channel order, float32 in [0, 1]."""
    raw = decode_image(path)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(raw.dtype)
    if scale is None:
        raise DatasetError(path, f"unsupported pixel type {raw.dtype}")
    if raw.ndim == 3 and raw.shape[2] == 3:
        raw = raw[..., ::-1]
    elif raw.ndim == 3 and raw.shape[2] == 4:
        raw = raw[..., [2, 1, 0, 3]]
    return np.ascontiguousarray(raw, dtype=np.float32) / np.float32(scale)


def read_png_uint8(path: Path) -> np.ndarray:
    """Decoded 8-bit PNG, RGB channel order, as stored (for encoded normal maps)."""
    raw = decode_image(path)
    if raw.dtype != np.uint8:
        raise DatasetError(path, f"must be an 8-bit PNG, got {raw.dtype}")
    if raw.ndim == 3 and raw.shape[2] >= 3:
        raw = raw[..., 2::-1]
    return np.ascontiguousarray(raw)


def write_png(path: Path, pixels: np.ndarray) -> None:
    """Write (H, W) or (H, W, 3) uint8 pixels (RGB order) as a PNG."""
    if pixels.dtype != np.uint8:
        raise TypeError(f"pixels for {path} must be uint8, got {pixels.dtype}")
    write_bgr_png(path, pixels[..., ::-1] if pixels.ndim == 3 else pixels)


def write_bgr_png(path: Path, pixels: np.ndarray) -> None:
    """Write (H, W) or (H, W, 3|4) uint8 pixels in OpenCV's BGR(A) order as a PNG, encoded
    in memory and written by Python (any path; a failed write raises ``OSError``)."""
    # Compression level 1: several times faster than the default at ~10 % larger files.
    ok, data = cv2.imencode(".png", np.ascontiguousarray(pixels), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"{path}: OpenCV cannot encode pixels of shape {pixels.shape} as PNG")
    write_bytes(path, data.tobytes())


def to_uint8(values: np.ndarray) -> np.ndarray:
    """Float values in [0, 1] → uint8 with rounding (values outside are clipped)."""
    return np.clip(np.rint(np.asarray(values, np.float32) * 255.0), 0, 255).astype(np.uint8)


def exr_size(path: Path) -> tuple[int, int]:
    """(width, height) from an EXR header (the pixels are not read), or a
    :class:`DatasetError`."""
    import OpenEXR

    if not path.is_file():
        raise MissingFileError(path, "file not found")
    try:
        with c_library_path(path, "r") as name, OpenEXR.File(name, header_only=True) as f:
            (x0, y0), (x1, y1) = f.header()["dataWindow"]
    except (RuntimeError, KeyError, ValueError) as e:
        raise DatasetError(path, f"not a readable EXR file ({e})") from None
    return int(x1 - x0 + 1), int(y1 - y0 + 1)


def read_exr_rgb(path: Path) -> np.ndarray:
    """The R, G, B channels of an EXR file (half or float) as (H, W, 3) float32."""
    import OpenEXR

    if not path.is_file():
        raise MissingFileError(path, "file not found")
    try:
        with c_library_path(path, "r") as name, OpenEXR.File(name, separate_channels=True) as f:
            channels = {name: c.pixels for name, c in f.channels().items()}
    except RuntimeError as e:
        raise DatasetError(path, f"not a readable EXR file ({e})") from None
    missing = [c for c in "RGB" if c not in channels]
    if missing:
        raise DatasetError(path, f"has no channel(s) {missing} (has {sorted(channels)})")
    return np.stack([channels[c] for c in "RGB"], -1).astype(np.float32)
