"""The error-driven sampling's per-frame bookkeeping in Rust (no gradients): a frame's
photometric error charged to a UV grid, and the nearest covered pixel of every pixel.
"Nearest" is OpenCV's labelled ``DIST_L2`` distance transform (a 5×5 chamfer metric within
~2 % of the Euclidean one), reproduced exactly, ties included."""

from __future__ import annotations

import math

import torch

from urhead.errors import DTypeError, ShapeError
from urhead.ops._bridge import check_shape, check_tensor, float_dtype, native, to_numpy


def accumulate_uv_error(
    image: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor,
    pixels: torch.Tensor,
    uv: torch.Tensor,
    error: torch.Tensor,
    count: torch.Tensor,
) -> None:
    """Adds one frame's error to the G × G UV grids ``error`` and ``count`` in place.

    Each pixel's error is ``‖image − target‖₁ · mask``. A covered pixel adds it, and 1 to
    the count, at the cell of the UV it sees (column ⌊u·G⌋, row ⌊(1 − v)·G⌋, clamped); a
    pixel inside the mask (``mask > 0.5``) that the mesh misses, at the cell of the nearest
    covered pixel's UV (:func:`nearest_covered_pixel`). Nothing is added when no pixel is
    covered. The sums run in a fixed order (covered pixels in ``pixels`` order, then missed
    ones row-major; the frame's sums then added to the grids), so the grids are bitwise
    those of ``torch.bincount`` over the same samples. Non-finite image values are data:
    the cells they reach become NaN or inf.

    Args:
        image, target: (H, W, 3) float32 or float64 (detached), the same dtype.
        mask: (H, W) in [0, 1], that dtype.
        pixels: (P,) int64 distinct flat indices of the covered pixels.
        uv: (P, 2) the UV each covered pixel sees, that float dtype.
        error, count: (G·G,) float64 grids, added to in place.
    """
    dtype = float_dtype("image", image)
    for name, t in (("target", target), ("mask", mask), ("uv", uv)):
        check_tensor(name, t)
        if t.dtype != dtype:
            raise DTypeError(f"{name} must have the dtype of image ({dtype}), got {t.dtype}")
    check_shape("error", error, 1, None, "(G·G,) float64")
    side = math.isqrt(error.numel())
    if side * side != error.numel():
        raise ShapeError(f"error must hold a square grid (G·G,), got {error.numel()} cells")
    native("accumulate_uv_error")(
        to_numpy("image", image.detach().contiguous(), dtype),
        to_numpy("target", target.detach().contiguous(), dtype),
        to_numpy("mask", mask.detach().contiguous(), dtype),
        to_numpy("pixels", pixels.contiguous(), torch.int64),
        to_numpy("uv", uv.detach().contiguous(), dtype),
        to_numpy("error", error, torch.float64),
        to_numpy("count", count, torch.float64),
        side,
    )


def nearest_covered_pixel(covered: torch.Tensor) -> torch.Tensor:
    """(H·W,) int64: for every pixel of the (H, W) bool ``covered``, the flat index of the
    nearest covered pixel (itself when covered); −1 everywhere when none is covered."""
    check_tensor("covered", covered)
    if covered.dtype != torch.bool:
        raise DTypeError(f"covered must be bool, got {covered.dtype}")
    check_shape("covered", covered, 2, None, "(H, W) bool")
    return torch.from_numpy(native("nearest_covered")(to_numpy("covered", covered, torch.bool)))
