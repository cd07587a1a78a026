"""urhead: photoreal, animatable head avatars from one monocular video, on the CPU.

A FLAME head mesh and 3D Gaussians share one set of UV maps and are optimised jointly
(the URHead method). Kernels are Rust with hand-written adjoints; see :mod:`urhead.ops`.
"""

from importlib.metadata import PackageNotFoundError, version

from urhead import ops
from urhead.camera import Camera

try:
    __version__ = version("urhead")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0"

__all__ = ["Camera", "__version__", "ops"]
