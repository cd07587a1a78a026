"""sh_shade: batched SH colour vs the plain-torch reference (float64 and float32), finite
differences, clamping, layout with extra channels, bad input."""

from __future__ import annotations

import pytest
import torch

from urhead.errors import DTypeError, InvalidArgumentError, NonFiniteError, ShapeError
from urhead.ops import _reference, sh_shade


def _case(n, stride, dtype, seed=0, scale=4.0):
    g = torch.Generator().manual_seed(seed)
    coeffs = ((torch.rand(n, stride, generator=g, dtype=torch.float64) - 0.5) * scale).to(dtype)
    dirs = torch.randn(n, 3, generator=g, dtype=torch.float64)
    dirs = (dirs / dirs.norm(dim=-1, keepdim=True)).to(dtype)
    return coeffs, dirs


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_matches_reference_forward_and_gradient_float64(degree):
    coeffs, dirs = _case(300, 3 * (degree + 1) ** 2 + 8, torch.float64)
    a = coeffs.clone().requires_grad_(True)
    b = coeffs.clone().requires_grad_(True)
    ours, ref = sh_shade(a, dirs, degree), _reference.sh_shade(b, dirs, degree)
    assert (ref == 0).any(), "some channels must clamp for the test to mean anything"
    assert torch.allclose(ours, ref, rtol=0, atol=1e-14)
    w = torch.randn(ours.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    (ours * w).sum().backward()
    (ref * w).sum().backward()
    assert torch.allclose(a.grad, b.grad, rtol=0, atol=1e-14)
    assert a.grad[:, 3 * (degree + 1) ** 2 :].eq(0).all()


def test_float32_agrees_with_float64():
    c64, d64 = _case(2000, 56, torch.float64, seed=3)
    got = sh_shade(c64.float(), d64.float(), 3).double()
    assert (got - sh_shade(c64, d64, 3)).abs().max() < 2e-6


def test_gradcheck():
    coeffs, dirs = _case(12, 50, torch.float64, seed=5, scale=0.1)
    coeffs = coeffs.requires_grad_(True)  # small coefficients: away from the clamp's kink
    assert torch.autograd.gradcheck(lambda c: sh_shade(c, dirs, 3), (coeffs,))


def test_bad_input():
    coeffs, dirs = _case(4, 48, torch.float32)
    with pytest.raises(InvalidArgumentError, match="degree"):
        sh_shade(coeffs, dirs, 4)
    with pytest.raises(InvalidArgumentError, match="coeffs"):
        sh_shade(coeffs[:, :40], dirs, 3)
    with pytest.raises(ShapeError, match="dirs"):
        sh_shade(coeffs, dirs[:3], 3)
    with pytest.raises(DTypeError, match="dirs"):
        sh_shade(coeffs, dirs.double(), 3)
    bad = dirs.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="dirs"):
        sh_shade(coeffs, bad, 3)
    assert torch.isnan(sh_shade(torch.full((1, 48), float("nan")), dirs[:1], 3)).all()


def test_same_bits_for_any_thread_count(monkeypatch):
    coeffs, dirs = _case(5000, 56, torch.float32, seed=9)
    weights = torch.rand(5000, 3, generator=torch.Generator().manual_seed(2))
    results = []
    for threads in ("1", "2", "4"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        x = coeffs.clone().requires_grad_(True)
        rgb = sh_shade(x, dirs, 3)
        (rgb * weights).sum().backward()
        results.append((rgb, x.grad))
    for rgb, grad in results[1:]:
        assert torch.equal(rgb, results[0][0]) and torch.equal(grad, results[0][1])


def test_backward_writes_the_rest_of_the_rows_gradient():
    """``sh_shade_backward``'s ``rest``: the other channels' gradient at its channels, the
    colour's unchanged; a misplaced or mis-sized one is refused."""
    from urhead.ops.shading import sh_shade_backward

    g = torch.Generator().manual_seed(3)
    coeffs = torch.randn(200, 27 + 5, generator=g)
    dirs = torch.nn.functional.normalize(torch.randn(200, 3, generator=g), dim=1)
    v_rgb = torch.randn(200, 3, generator=g)
    rest = torch.randn(200, 4, generator=g)
    plain = sh_shade_backward(coeffs, dirs, 2, v_rgb)
    full = sh_shade_backward(coeffs, dirs, 2, v_rgb, (rest, 28))
    expected = plain.clone()
    expected[:, 28:32] = rest
    assert torch.equal(full, expected)
    with pytest.raises(InvalidArgumentError, match="rest"):
        sh_shade_backward(coeffs, dirs, 2, v_rgb, (rest, 26))  # inside the colour
    with pytest.raises(InvalidArgumentError, match="rest"):
        sh_shade_backward(coeffs, dirs, 2, v_rgb, (rest, 29))  # past the rows
    with pytest.raises((ShapeError, InvalidArgumentError), match="rest"):
        sh_shade_backward(coeffs, dirs, 2, v_rgb, (rest[1:], 28))
