"""urhead: photoreal, animatable head avatars from one monocular video, on the CPU.

A FLAME head mesh and 3D Gaussians share one set of UV maps and are optimised jointly
(the URHead method). Kernels are Rust with hand-written adjoints; see :mod:`urhead.ops`.

``urhead.ops`` and ``urhead.Camera`` are loaded on first use: they import torch, which
the command line's ``--help`` and ``--version`` do not need.
"""

import importlib
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("urhead")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0"

__all__ = ["Camera", "__version__", "ops"]


def __getattr__(name: str):
    if name == "ops":
        return importlib.import_module("urhead.ops")
    if name == "Camera":
        return importlib.import_module("urhead.camera").Camera
    raise AttributeError(f"module 'urhead' has no attribute {name!r}")
