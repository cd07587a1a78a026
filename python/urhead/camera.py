"""The one camera type every op takes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from urhead.errors import DTypeError, ShapeError


def _matrix(name: str, value, shape: tuple[int, int]) -> torch.Tensor:
    t = value if isinstance(value, torch.Tensor) else torch.as_tensor(value)
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise DTypeError(f"{name} must be a float tensor, got {t.dtype}")
    if tuple(t.shape) != shape:
        raise ShapeError(f"{name} must be {shape}, got {tuple(t.shape)}")
    return t.detach().to(device="cpu", dtype=torch.float32).contiguous()


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: OpenCV axes (x right, y down, z forward), ``K`` (3, 3) intrinsics
    in pixels, ``viewmat`` (4, 4) world→camera, pixel centres at (x + 0.5, y + 0.5),
    linear view-space depth clipped to [near, far].

    Validated on construction (finite, positive focal lengths, no skew, a rigid-style last
    row, a sane image size) with the same check every kernel uses. Stored as float32.
    Cameras are constants: no gradient flows to ``K`` or ``viewmat``.
    """

    K: torch.Tensor
    viewmat: torch.Tensor
    width: int
    height: int
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self):
        object.__setattr__(self, "K", _matrix("K", self.K, (3, 3)))
        object.__setattr__(self, "viewmat", _matrix("viewmat", self.viewmat, (4, 4)))
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise DTypeError(f"{name} must be an int, got {type(value).__name__}")
        object.__setattr__(self, "near", float(self.near))
        object.__setattr__(self, "far", float(self.far))
        # Imported here: urhead.ops imports this module.
        from urhead.ops._bridge import native

        native("check_camera")(self.core_args())

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for an image resampled to ``width`` × ``height``: focal lengths
        and principal point scale with the image (pixel centres stay at x + 0.5)."""
        k = self.K.clone()
        k[0] *= width / self.width
        k[1] *= height / self.height
        return Camera(k, self.viewmat, int(width), int(height), self.near, self.far)

    def core_args(self) -> tuple:
        """The tuple the Rust kernels take."""
        return (
            self.K.tolist(),
            self.viewmat.tolist(),
            self.width,
            self.height,
            self.near,
            self.far,
        )

    def to_dict(self) -> dict:
        """JSON-ready fields (``from_dict`` inverts it)."""
        return {
            "K": self.K.tolist(),
            "viewmat": self.viewmat.tolist(),
            "width": self.width,
            "height": self.height,
            "near": self.near,
            "far": self.far,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(d["K"], d["viewmat"], int(d["width"]), int(d["height"]), d["near"], d["far"])

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def center(self) -> torch.Tensor:
        """(3,) camera centre in world space."""
        r, t = self.viewmat[:3, :3].double(), self.viewmat[:3, 3].double()
        return (-r.T @ t).float()

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) world points → (..., 3) camera-space points."""
        v = self.viewmat.to(points.dtype)
        return points @ v[:3, :3].T + v[:3, 3]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) world points → ((..., 2) pixel coordinates, (...,) linear depth)."""
        c = self.world_to_camera(points)
        k = self.K.to(points.dtype)
        z = c[..., 2]
        uv = torch.stack([k[0, 0] * c[..., 0] / z + k[0, 2], k[1, 1] * c[..., 1] / z + k[1, 2]], -1)
        return uv, z

    @classmethod
    def look_at(
        cls,
        eye,
        target,
        up=(0.0, 1.0, 0.0),
        *,
        fov_y_degrees: float = 20.0,
        width: int = 512,
        height: int = 512,
        near: float = 0.01,
        far: float = 100.0,
    ) -> Camera:
        """A centred camera at ``eye`` looking at ``target``; ``up`` is world up (image up)."""
        eye_t = torch.as_tensor(eye, dtype=torch.float64)
        forward = torch.as_tensor(target, dtype=torch.float64) - eye_t
        forward = forward / forward.norm()
        right = torch.linalg.cross(forward, torch.as_tensor(up, dtype=torch.float64))
        if right.norm() < 1e-9:
            raise ValueError("look_at: up is parallel to the viewing direction")
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        rot = torch.stack([right, down, forward])  # rows: camera axes in world space
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3, :3] = rot
        viewmat[:3, 3] = -rot @ eye_t
        focal = 0.5 * height / math.tan(math.radians(fov_y_degrees) / 2)
        k = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
        return cls(k, viewmat, width, height, near, far)

    @classmethod
    def from_opengl_c2w(
        cls,
        c2w,
        fl_x: float,
        fl_y: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        near: float = 0.01,
        far: float = 100.0,
    ) -> Camera:
        """From a camera-to-world matrix in OpenGL axes (x right, y up, z back), as in
        NeRF-style ``transforms.json``: flip the y and z axes, then invert."""
        c2w_cv = torch.as_tensor(c2w, dtype=torch.float64).clone()
        if tuple(c2w_cv.shape) != (4, 4):
            raise ShapeError(f"c2w must be (4, 4), got {tuple(c2w_cv.shape)}")
        c2w_cv[:3, 1:3] *= -1
        k = torch.tensor([[fl_x, 0, cx], [0, fl_y, cy], [0, 0, 1]], dtype=torch.float64)
        return cls(k, torch.linalg.inv(c2w_cv), width, height, near, far)
