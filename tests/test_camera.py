"""urhead.Camera: conventions (OpenCV axes, pixel centres) and validation."""

import pytest
import torch

from urhead import Camera
from urhead.errors import DTypeError, InvalidArgumentError, ShapeError


def test_look_at_projects_world_axes_the_opencv_way():
    cam = Camera.look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), width=64, height=48)
    uv, depth = cam.project(torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]]))
    assert torch.allclose(uv[0], torch.tensor([32.0, 24.0]))
    assert uv[1, 0] > 32  # world +x is image right
    assert uv[2, 1] < 24  # world +y (up) is image up, i.e. smaller rows
    assert torch.allclose(depth, torch.ones(3))
    assert torch.allclose(cam.center, torch.tensor([0.0, 0, 1]), atol=1e-6)


def test_opengl_camera_to_world_conversion():
    # An OpenGL camera at z = 2 looking down -z (identity rotation).
    c2w = torch.eye(4)
    c2w[2, 3] = 2.0
    cam = Camera.from_opengl_c2w(c2w, fl_x=100, fl_y=120, cx=30.5, cy=20.25, width=64, height=48)
    uv, depth = cam.project(torch.tensor([[0.0, 0, 0], [0.1, 0.1, 0]]))
    assert torch.allclose(uv[0], torch.tensor([30.5, 20.25]))  # off-centre principal point
    assert torch.allclose(uv[1], torch.tensor([30.5 + 5.0, 20.25 - 6.0]))
    assert torch.allclose(depth, torch.full((2,), 2.0))


@pytest.mark.parametrize(
    ("kwargs", "error", "pattern"),
    [
        ({"K": torch.eye(4)}, ShapeError, "K must be"),
        ({"viewmat": torch.eye(3)}, ShapeError, "viewmat must be"),
        (
            {"K": torch.tensor([[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]])},
            InvalidArgumentError,
            "K",
        ),
        ({"K": torch.tensor([[-1.0, 0, 1], [0, 1, 1], [0, 0, 1]])}, InvalidArgumentError, "K"),
        ({"viewmat": torch.full((4, 4), float("inf"))}, InvalidArgumentError, "viewmat"),
        ({"width": 0}, InvalidArgumentError, "width"),
        ({"height": 10**6}, InvalidArgumentError, "height"),
        ({"width": 3.5}, DTypeError, "width"),
        ({"near": 0.0}, InvalidArgumentError, "near"),
        ({"near": 1.0, "far": 0.5}, InvalidArgumentError, "near"),
    ],
)
def test_invalid_cameras_are_named(kwargs, error, pattern):
    args = {
        "K": torch.tensor([[50.0, 0, 16], [0, 50, 16], [0, 0, 1]]),
        "viewmat": torch.eye(4),
        "width": 32,
        "height": 32,
    }
    args.update(kwargs)
    with pytest.raises(error, match=pattern):
        Camera(**args)
