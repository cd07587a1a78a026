"""Writing MP4 files (OpenCV's ``mp4v`` encoder) atomically."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from urhead.use.common import write_file_atomically


def write_mp4(path: Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Writes (H, W, 3) uint8 BGR frames (all one size) to ``path``; returns the count."""
    count = 0

    def write(tmp: Path) -> None:
        nonlocal count
        writer = None
        try:
            for frame in frames:
                if writer is None:
                    h, w = frame.shape[:2]
                    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
                    if not writer.isOpened():
                        raise OSError(f"{path}: OpenCV cannot open an mp4v video writer")
                writer.write(frame)
                count += 1
        finally:
            if writer is not None:
                writer.release()
        if count == 0:
            raise ValueError(f"{path}: no frames to write")

    write_file_atomically(Path(path), write)
    return count
