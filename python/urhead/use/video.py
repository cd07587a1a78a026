"""Writing MP4 files atomically: H.264 (yuv420p, ``+faststart``) through PyAV, which
browsers and repository previews play; OpenCV's MPEG-4 Part 2 (``mp4v``) only when PyAV or
its H.264 encoder is missing, with a note on stderr."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from fractions import Fraction
from pathlib import Path

import numpy as np

from urhead._atomic import c_library_path, write_file_atomically

H264_CRF = 18
"""x264's constant-rate factor: 18 is visually lossless for these renders."""


def write_mp4(path: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Writes (H, W, 3) uint8 BGR frames (all one size) to ``path``; returns the count.
    Odd sizes are padded by one edge row / column (H.264 in 4:2:0 needs even sizes)."""
    path = Path(path)
    encoder = _h264_available()
    count = 0

    def counted() -> Iterator[np.ndarray]:
        nonlocal count
        for frame in frames:
            count += 1
            yield frame

    def write(tmp: Path) -> None:
        with c_library_path(tmp, "w") as name:
            if encoder:
                _write_h264(name, counted(), fps)
            else:
                _write_mp4v(name, counted(), fps, path)
            if count == 0:
                raise ValueError(f"{path}: no frames to write")
            _check_frame_count(name, count, path)

    if not encoder:
        print(f"{path}: PyAV with H.264 is not available, writing mp4v", file=sys.stderr)
    write_file_atomically(path, write)
    return count


def _h264_available() -> bool:
    try:
        import av
    except ImportError:
        return False
    return "libx264" in av.codecs_available or "h264" in av.codecs_available


def _check_frame_count(name: str, count: int, path: Path) -> None:
    """The written file's index must list ``count`` frames (a truncated file has none)."""
    import cv2

    video = cv2.VideoCapture(name)
    try:
        found = int(video.get(cv2.CAP_PROP_FRAME_COUNT)) if video.isOpened() else 0
    finally:
        video.release()
    if found != count:
        raise OSError(f"{path}: the video written holds {found} of {count} frames")


def _write_h264(tmp: str, frames: Iterator[np.ndarray], fps: float) -> None:
    import av

    rate = Fraction(fps).limit_denominator(1001)
    with av.open(tmp, mode="w", format="mp4", options={"movflags": "+faststart"}) as out:
        stream = None
        for frame in frames:
            even = _pad_to_even(frame)
            if stream is None:
                stream = out.add_stream("libx264", rate=rate, options={"crf": str(H264_CRF)})
                stream.height, stream.width = even.shape[:2]
                stream.pix_fmt = "yuv420p"
            picture = av.VideoFrame.from_ndarray(even, format="bgr24")
            out.mux(stream.encode(picture))
        if stream is not None:
            out.mux(stream.encode(None))  # flush the encoder's delayed frames


def _write_mp4v(tmp: str, frames: Iterator[np.ndarray], fps: float, path: Path) -> None:
    import cv2

    writer = None
    try:
        for frame in frames:
            if writer is None:
                h, w = frame.shape[:2]
                writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
                if not writer.isOpened():
                    raise OSError(f"{path}: OpenCV cannot open an mp4v video writer")
            writer.write(frame)
    finally:
        if writer is not None:
            writer.release()


def _pad_to_even(frame: np.ndarray) -> np.ndarray:
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return np.ascontiguousarray(frame)
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
