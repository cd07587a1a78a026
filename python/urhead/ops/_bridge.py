"""The one way into the Rust extension (``urhead._core``): its entry points by name, and
the tensor checks only Python can make before zero-copy numpy views are handed over.
Which layer checks what is written once, in the binding's ``rust/urhead-py/src/lib.rs``."""

from __future__ import annotations

import numpy as np
import torch

from urhead import _core
from urhead.camera import Camera
from urhead.errors import DTypeError, InvalidArgumentError, ShapeError

FLOAT_DTYPES = (torch.float32, torch.float64)


def float_dtype(name: str, t: torch.Tensor) -> torch.dtype:
    """The dtype of the float tensor ``t``; the one every other float argument must share."""
    check_tensor(name, t)
    if t.dtype not in FLOAT_DTYPES:
        raise DTypeError(f"{name} must be float32 or float64, got {t.dtype}")
    return t.dtype


def check_tensor(name: str, t: object) -> None:
    # Called ~100 times a frame: `is_cpu` and one layout test (sparse layouts included)
    # cost a third of `device.type` and `is_sparse`.
    if not isinstance(t, torch.Tensor):
        raise DTypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if not t.is_cpu:
        raise DTypeError(f"{name} must be on the CPU, got device {t.device}")
    if t.layout != torch.strided:
        raise DTypeError(f"{name} must be a dense (strided) tensor, got layout {t.layout}")


def to_numpy(name: str, t: torch.Tensor, dtype: torch.dtype) -> np.ndarray:
    """A zero-copy numpy view of ``t``; ``t`` must be a contiguous CPU tensor of ``dtype``."""
    check_tensor(name, t)
    if t.dtype != dtype:
        raise DTypeError(f"{name} must be {dtype}, got {t.dtype}")
    if not t.is_contiguous():
        raise InvalidArgumentError(f"{name} must be contiguous; call .contiguous() first")
    return t.detach().numpy()


def grad_to_numpy(name: str, g: torch.Tensor | None, dtype: torch.dtype) -> np.ndarray | None:
    """Incoming gradients may be non-contiguous or broadcast views; those are copied."""
    if g is None:
        return None
    return g.detach().to(dtype).contiguous().numpy()


def from_numpy(a: np.ndarray | None) -> torch.Tensor | None:
    return None if a is None else torch.from_numpy(a)


def native(name: str):
    """The Rust entry point (function or class) ``name`` of ``urhead._core``; a kernel's
    entry serves float32 and float64 (the dtype of its first float array)."""
    return getattr(_core, name)


def index_tensor(name: str, t: torch.Tensor) -> torch.Tensor:
    """``t`` as int32; other integer dtypes are converted (face tables are small)."""
    check_tensor(name, t)
    if t.dtype == torch.int32:
        return t
    if t.dtype in (torch.int64, torch.int16, torch.uint8, torch.int8):
        if t.numel() and (int(t.max()) > 2**31 - 1 or int(t.min()) < -(2**31)):
            raise DTypeError(f"{name} holds values outside the int32 range")
        return t.to(torch.int32)
    raise DTypeError(f"{name} must be an integer tensor (int32), got {t.dtype}")


def check_shape(name: str, t: torch.Tensor, ndim: int, last: int | None, layout: str) -> None:
    if t.dim() != ndim or (last is not None and t.shape[-1] != last):
        raise ShapeError(f"{name} must be {layout}, got {tuple(t.shape)}")


def check_camera(camera: object) -> Camera:
    if not isinstance(camera, Camera):
        raise DTypeError(f"camera must be a urhead.Camera, got {type(camera).__name__}")
    return camera
