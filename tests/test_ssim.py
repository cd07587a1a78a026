"""urhead.ops.masked_ssim / masked_l1 (and the two in one pass, masked_ssim_l1) against the
plain-torch references (value and gradient), finite differences, edge cases, input errors and
thread-count determinism."""

from __future__ import annotations

import pytest
import torch

from urhead.errors import (
    DTypeError,
    IndexRangeError,
    InvalidArgumentError,
    NonFiniteError,
    ShapeError,
)
from urhead.losses import l1, ssim, ssim_l1
from urhead.ops import _reference as ref
from urhead.ops import masked_l1, masked_pixel_l1, masked_ssim, masked_ssim_l1

OPS = {"ssim": (masked_ssim, ref.masked_ssim), "l1": (masked_l1, ref.masked_l1)}


def images(h, w, c=3, dtype=torch.float64, seed=0, noise=0.15):
    """A target and a nearby image, as a render and its photo."""
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    image = (target + noise * torch.randn(h, w, c, generator=g, dtype=torch.float64)).clamp(0, 1)
    return image.to(dtype), target.to(dtype)


def make_mask(kind, h, w, dtype=torch.float64, seed=1):
    g = torch.Generator().manual_seed(seed)
    if kind == "none":
        return None
    if kind == "binary":
        return torch.rand(h, w, generator=g) > 0.4
    if kind == "soft":
        return torch.rand(h, w, generator=g, dtype=torch.float64).to(dtype)
    if kind == "zero":
        return torch.zeros(h, w, dtype=dtype)
    if kind == "pixel":
        m = torch.zeros(h, w, dtype=dtype)
        m[h // 2, w // 3] = 1
        return m
    raise ValueError(kind)


def value_and_grad(fn, image, target, mask):
    x = image.clone().requires_grad_(True)
    value = fn(x, target, mask)
    value.backward()
    return value.detach(), x.grad


@pytest.mark.parametrize("op", OPS)
@pytest.mark.parametrize("mask_kind", ["none", "binary", "soft", "zero", "pixel"])
@pytest.mark.parametrize("shape", [(1, 1, 3), (5, 7, 3), (37, 150, 3), (140, 23, 1)])
def test_float64_matches_reference(op, mask_kind, shape):
    image, target = images(*shape)
    mask = make_mask(mask_kind, *shape[:2])
    ours, ref_fn = OPS[op]
    value, grad = value_and_grad(ours, image, target, mask)
    ref_value, ref_grad = value_and_grad(ref_fn, image, target, mask)
    assert value.dtype == torch.float64 and value.shape == ()
    assert abs(value.item() - ref_value.item()) < 1e-14
    assert (grad - ref_grad).abs().max().item() < 2e-15
    if mask_kind == "zero":
        assert value.item() == 0 and grad.abs().max().item() == 0


@pytest.mark.parametrize("op", OPS)
def test_float32_matches_reference(op):
    image, target = images(96, 131, dtype=torch.float32, seed=3)
    mask = make_mask("soft", 96, 131, torch.float32)
    ours, ref_fn = OPS[op]
    value, grad = value_and_grad(ours, image, target, mask)
    ref_value, ref_grad = value_and_grad(ref_fn, image.double(), target.double(), mask.double())
    assert grad.dtype == torch.float32
    # torch's own float32 evaluation is off by up to 6e-8 (value) and 7e-7 (gradient)
    assert abs(value.item() - ref_value.item()) < 1e-7 * abs(ref_value.item())
    scale = ref_grad.abs().max().item()
    assert (grad.double() - ref_grad).abs().max().item() < 1e-6 * scale


@pytest.mark.parametrize("mask_kind", ["none", "soft"])
def test_ssim_gradient_matches_finite_differences(mask_kind):
    image, target = images(23, 31, seed=5)
    mask = make_mask(mask_kind, 23, 31)
    _, grad = value_and_grad(masked_ssim, image, target, mask)
    g = torch.Generator().manual_seed(7)
    eps = 1e-6
    for _ in range(4):
        direction = torch.randn(image.shape, generator=g, dtype=torch.float64)
        plus = masked_ssim(image + eps * direction, target, mask).item()
        minus = masked_ssim(image - eps * direction, target, mask).item()
        fd = (plus - minus) / (2 * eps)
        analytic = (grad * direction).sum().item()
        assert abs(fd - analytic) < 2e-8 * max(abs(analytic), 1e-3)


def test_identical_images_score_one_with_zero_gradient():
    _, target = images(40, 41)
    value, grad = value_and_grad(masked_ssim, target, target, make_mask("soft", 40, 41))
    assert abs(value.item() - 1) < 1e-14
    assert grad.abs().max().item() == 0  # SSIM's maximum, not its rounding
    value, grad = value_and_grad(masked_l1, target, target, None)
    assert value.item() == 0 and grad.abs().max().item() == 0


def render_on_background(h=150, w=90, dtype=torch.float64):
    """A photo of a head on a white background and a render of it that matches the
    background exactly and the head only nearly (as a fit's), the head's mask, and the
    pixels far from the head."""
    g = torch.Generator().manual_seed(11)
    y, x = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    head = ((y - 70) / 45.0) ** 2 + ((x - 40) / 25.0) ** 2 < 1
    target = torch.ones(h, w, 3, dtype=torch.float64)
    target[head] = torch.rand(int(head.sum()), 3, generator=g, dtype=torch.float64)
    image = target.clone()
    image[head] = (
        target[head] + 0.1 * torch.randn(target[head].shape, generator=g, dtype=torch.float64)
    ).clamp(0, 1)
    # Columns more than two blur radii (10 px) from the head's: the kernel's bands skip them.
    columns = head.any(0).nonzero().flatten()
    far = (x < columns.min() - 10) | (x > columns.max() + 10)
    return image.to(dtype), target.to(dtype), head.to(dtype), far


@pytest.mark.parametrize("masked", [False, True])
def test_a_render_on_the_photos_background_matches_the_reference(masked):
    """The kernel skips columns where the image equals the target over a whole window
    (SSIM exactly 1, its gradient exactly 0) or the mask is 0: the same value and gradient
    as the reference, and an exactly zero gradient beyond the head's reach."""
    image, target, head, far = render_on_background()
    mask = head if masked else None
    value, grad = value_and_grad(masked_ssim, image, target, mask)
    ref_value, ref_grad = value_and_grad(ref.masked_ssim, image, target, mask)
    assert abs(value.item() - ref_value.item()) < 1e-14
    assert (grad - ref_grad).abs().max().item() < 2e-15
    assert grad[far].abs().max().item() == 0
    # The training loss, in float32, as the fit calls it (no mask).
    image32, target32 = image.float(), target.float()
    x = image32.clone().requires_grad_(True)
    ssim_l1(x, target32, ssim_weight=-0.2, l1_weight=0.64).backward()
    x64 = image.clone().requires_grad_(True)
    (-0.2 * ref.masked_ssim(x64, target) + 0.64 * ref.masked_l1(x64, target)).backward()
    # float32 against the float64 reference: SSIM's variances cancel in float32
    assert (x.grad.double() - x64.grad).abs().max().item() < 1e-4 * x64.grad.abs().max().item()
    assert x.grad[far].abs().max().item() == 0


def test_constant_images_follow_the_luminance_term():
    # σ = 0 everywhere, so SSIM = (2·a·b + C1) / (a² + b² + C1) away from the zero border.
    a, b = 0.6, 0.3
    image = torch.full((30, 30, 3), a, dtype=torch.float64)
    target = torch.full((30, 30, 3), b, dtype=torch.float64)
    inner = torch.zeros(30, 30, dtype=torch.float64)
    inner[5:-5, 5:-5] = 1
    expected = (2 * a * b + 1e-4) / (a * a + b * b + 1e-4)
    assert abs(masked_ssim(image, target, inner).item() - expected) < 1e-12
    value, grad = value_and_grad(masked_ssim, image, target, None)
    ref_value, ref_grad = value_and_grad(ref.masked_ssim, image, target, None)
    assert abs(value.item() - ref_value.item()) < 1e-13
    assert (grad - ref_grad).abs().max().item() < 1e-13


def test_losses_module_uses_the_kernel_and_keeps_plain_torch_semantics():
    image, target = images(33, 45, dtype=torch.float32, seed=9)
    mask = make_mask("binary", 33, 45)
    x = image.clone().requires_grad_(True)
    (ssim(x, target, mask) + l1(x, target, mask)).backward()
    x_ref = image.double().clone().requires_grad_(True)
    (
        ref.masked_ssim(x_ref, target.double(), mask) + ref.masked_l1(x_ref, target.double(), mask)
    ).backward()
    assert (x.grad.double() - x_ref.grad).abs().max().item() < 1e-7
    # a target that requires grad falls back to plain torch and receives a gradient
    y = target.clone().requires_grad_(True)
    ssim(image, y, mask).backward()
    assert y.grad is not None and y.grad.abs().sum() > 0


def test_thread_count_does_not_change_bits(monkeypatch):
    image, target = images(300, 70, dtype=torch.float32, seed=11)
    mask = make_mask("soft", 300, 70, torch.float32)
    results = []
    for threads in ("1", "2", "4"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        results.append(
            [t for fn in (masked_ssim, masked_l1) for t in value_and_grad(fn, image, target, mask)]
        )
    for other in results[1:]:
        for a, b in zip(results[0], other, strict=True):
            assert torch.equal(a, b)


def test_scaled_loss_scales_the_gradient():
    image, target = images(12, 19, seed=13)
    _, grad = value_and_grad(masked_ssim, image, target, None)
    x = image.clone().requires_grad_(True)
    (0.2 * (1 - masked_ssim(x, target))).backward()
    assert torch.allclose(x.grad, -0.2 * grad, rtol=1e-15, atol=0)


@pytest.mark.parametrize("op", OPS)
@pytest.mark.parametrize("weight", [0.64, -0.2, 0.0, 3.0])
def test_a_weight_scales_the_value_and_the_kernels_gradient(op, weight):
    """``weight`` multiplies the value and, inside the kernel, the gradient: a summed loss
    of weighted terms hands that gradient back as computed, unscaled by the backward."""
    from urhead.ops._bridge import native

    kernel, reference = OPS[op]
    image, target = images(17, 23, dtype=torch.float32, seed=21)
    mask = make_mask("soft", 17, 23, torch.float32)
    value, grad = value_and_grad(kernel, image, target, mask)
    x = image.clone().requires_grad_(True)
    weighted = kernel(x, target, mask, weight=weight)
    (weighted + 0.5).backward()  # the incoming gradient is exactly 1
    assert weighted.item() == pytest.approx(weight * value.item(), rel=1e-6, abs=1e-12)
    _, in_kernel = native("masked_mean_grad")(
        op, image.numpy(), target.numpy(), mask.numpy(), weight, 1
    )
    assert torch.equal(x.grad, torch.from_numpy(in_kernel))
    largest = abs(weight) * grad.abs().max().item()
    assert (x.grad - weight * grad).abs().max().item() <= 1e-5 * largest
    # the same through the plain-torch reference, in float64
    x_ref = image.double().requires_grad_(True)
    (weight * reference(x_ref, target.double(), mask.double())).backward()
    assert (x.grad.double() - x_ref.grad).abs().max().item() < 1e-7
    # an incoming gradient other than 1 still scales it
    x2 = image.clone().requires_grad_(True)
    (3 * kernel(x2, target, mask, weight=weight)).backward()
    assert torch.allclose(x2.grad, 3 * x.grad, rtol=1e-6, atol=0)


@pytest.mark.parametrize("op", [masked_ssim, masked_l1])
@pytest.mark.parametrize("weight", [float("nan"), float("inf"), True, "0.5", None])
def test_a_weight_must_be_a_finite_number(op, weight):
    image, target = images(8, 9)
    with pytest.raises(InvalidArgumentError, match="weight"):
        op(image, target, weight=weight)


def test_the_losses_module_weights_its_plain_torch_fallback_too():
    image, target = images(14, 15, seed=23)
    y = target.clone().requires_grad_(True)  # a target with gradient: the fallback
    for fn in (ssim, l1):
        assert fn(image, y, weight=0.3).item() == pytest.approx(0.3 * fn(image, y).item())


def test_no_grad_needed_returns_the_same_value():
    image, target = images(20, 20, seed=15)
    with_grad = masked_ssim(image.clone().requires_grad_(True), target)
    assert masked_ssim(image, target).item() == with_grad.item()
    assert not masked_ssim(image, target).requires_grad


@pytest.mark.parametrize("op", [masked_ssim, masked_l1])
def test_bad_inputs_raise_typed_errors_naming_the_argument(op):
    image, target = images(8, 9)
    bad = image.clone()
    bad[2, 3, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="image"):
        op(bad, target)
    bad_target = target.clone()
    bad_target[0, 0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match="target"):
        op(image, bad_target)
    nan_mask = torch.ones(8, 9, dtype=torch.float64)
    nan_mask[1, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="mask"):
        op(image, target, nan_mask)
    with pytest.raises(InvalidArgumentError, match="mask"):
        op(image, target, torch.full((8, 9), 1.5, dtype=torch.float64))
    with pytest.raises(ShapeError, match="target"):
        op(image, target[:, :8].contiguous())
    with pytest.raises(ShapeError, match="mask"):
        op(image, target, torch.ones(9, 8, dtype=torch.float64))
    with pytest.raises(ShapeError, match="image"):
        op(image[..., 0].contiguous(), target[..., 0].contiguous())
    with pytest.raises(ShapeError, match="image"):
        op(image[:0].contiguous(), target[:0].contiguous())
    with pytest.raises(DTypeError, match="target"):
        op(image, target.float())
    with pytest.raises(DTypeError, match="image"):
        op(image.half(), target.half())
    with pytest.raises(InvalidArgumentError, match="contiguous"):
        op(image.transpose(0, 1), target.transpose(0, 1))
    with pytest.raises(InvalidArgumentError, match="target"):
        op(image, target.clone().requires_grad_(True))


@pytest.mark.parametrize("channels, extra", [(3, 1), (1, 2), (2, 3)])
@pytest.mark.parametrize("mask_kind", ["none", "soft"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_l1_reads_the_first_channels_of_a_wider_image_in_place(channels, extra, mask_kind, dtype):
    """A wider image against a target (the mesh term: RGBA against RGB, the kernel's
    fixed-size path; other widths take its general one): the value and the compared
    channels' gradient are those of those channels alone, bit for bit; the rest get none."""
    rgb, target = images(37, 141, channels, dtype=dtype, seed=5)
    more = torch.rand(37, 141, extra, generator=torch.Generator().manual_seed(6), dtype=dtype)
    rgba = torch.cat([rgb, more], -1)
    mask = make_mask(mask_kind, 37, 141, dtype)
    wide_value, wide_grad = value_and_grad(masked_l1, rgba, target, mask)
    value, grad = value_and_grad(masked_l1, rgb, target, mask)
    assert wide_grad.shape == (37, 141, channels + extra)
    assert wide_grad[..., channels:].eq(0).all()
    assert torch.equal(wide_value, value) and torch.equal(wide_grad[..., :channels], grad)
    ref_value, ref_grad = value_and_grad(ref.masked_l1, rgba, target, mask)
    assert torch.allclose(wide_value, ref_value, rtol=1e-12 if dtype == torch.float64 else 1e-5)
    assert torch.allclose(wide_grad, ref_grad)
    assert torch.equal(l1(rgba, target, mask), wide_value)  # the losses module takes it too
    with pytest.raises(ShapeError, match="target"):
        masked_ssim(rgba, target)  # SSIM compares whole images
    with pytest.raises(ShapeError, match="target"):
        masked_l1(rgb, torch.cat([target, target[..., :1]], -1))  # fewer than the target


@pytest.mark.parametrize("mask_kind", ["none", "binary", "soft", "zero"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("weights", [(-0.2, 0.64), (1.0, 1.0), (0.0, 2.5), (0.7, 0.0)])
def test_ssim_and_l1_in_one_pass_are_the_two_ops_apart(mask_kind, dtype, weights):
    """The value is ``ssim_weight·SSIM + l1_weight·L1`` and the gradient is, bit for bit,
    the sum of the two ops' (the kernel returns each term's value apart too); both follow
    the float64 plain-torch references."""
    from urhead.ops._bridge import native

    ssim_weight, l1_weight = weights
    image, target = images(37, 29, dtype=dtype, seed=31)
    mask = make_mask(mask_kind, 37, 29, dtype)
    x = image.clone().requires_grad_(True)
    fused = masked_ssim_l1(x, target, mask, ssim_weight=ssim_weight, l1_weight=l1_weight)
    (fused + 0.5).backward()
    apart = [image.clone().requires_grad_(True) for _ in range(2)]
    s_value = masked_ssim(apart[0], target, mask, weight=ssim_weight)
    l_value = masked_l1(apart[1], target, mask, weight=l1_weight)
    (s_value + l_value).backward()
    # the terms summed in float64 before the value is rounded to the images' dtype
    assert fused.item() == pytest.approx(s_value.item() + l_value.item(), rel=1e-7, abs=1e-9)
    assert torch.equal(x.grad, apart[0].grad + apart[1].grad)
    m = None if mask is None else mask.to(dtype).numpy()
    ssim_alone, l1_alone, _ = native("masked_ssim_l1_grad")(
        image.numpy(), target.numpy(), m, ssim_weight, l1_weight, 1
    )
    assert ssim_alone == masked_ssim(image, target, mask).item()
    assert l1_alone == masked_l1(image, target, mask).item()
    x_ref = image.double().requires_grad_(True)
    m_ref = None if mask is None else mask.double()
    ref_loss = ssim_weight * ref.masked_ssim(x_ref, target.double(), m_ref)
    ref_loss = ref_loss + l1_weight * ref.masked_l1(x_ref, target.double(), m_ref)
    ref_loss.backward()
    tolerance = 1e-12 if dtype == torch.float64 else 2e-6
    assert fused.item() == pytest.approx(ref_loss.item(), abs=tolerance)
    assert (x.grad.double() - x_ref.grad).abs().max().item() < tolerance


def test_ssim_and_l1_in_one_pass_scale_by_an_incoming_gradient_and_skip_it_unasked():
    image, target = images(21, 18, seed=33)
    x = image.clone().requires_grad_(True)
    masked_ssim_l1(x, target, ssim_weight=-0.2, l1_weight=0.8).backward()
    x3 = image.clone().requires_grad_(True)
    (3 * masked_ssim_l1(x3, target, ssim_weight=-0.2, l1_weight=0.8)).backward()
    assert torch.allclose(x3.grad, 3 * x.grad, rtol=1e-12, atol=0)
    value = masked_ssim_l1(image, target, ssim_weight=-0.2, l1_weight=0.8)
    assert not value.requires_grad
    expected = -0.2 * masked_ssim(image, target).item() + 0.8 * masked_l1(image, target).item()
    assert value.item() == expected


@pytest.mark.parametrize("name", ["ssim_weight", "l1_weight"])
@pytest.mark.parametrize("weight", [float("nan"), float("inf"), True, "0.5", None])
def test_ssim_and_l1_weights_must_be_finite_numbers(name, weight):
    image, target = images(8, 9)
    weights = {"ssim_weight": 1.0, "l1_weight": 1.0, name: weight}
    with pytest.raises(InvalidArgumentError, match=name):
        masked_ssim_l1(image.requires_grad_(True), target, **weights)


def test_ssim_and_l1_in_one_pass_refuse_what_ssim_refuses():
    image, target = images(8, 9)
    bad = image.clone()
    bad[2, 3, 1] = float("nan")
    with pytest.raises(NonFiniteError, match="image"):
        masked_ssim_l1(bad.requires_grad_(True), target, ssim_weight=1.0, l1_weight=1.0)
    rgba = torch.cat([image, torch.ones(8, 9, 1, dtype=image.dtype)], -1)
    with pytest.raises(ShapeError, match="target"):  # SSIM compares whole images
        masked_ssim_l1(rgba.requires_grad_(True), target, ssim_weight=1.0, l1_weight=1.0)


def test_the_losses_module_ssim_l1_is_the_two_terms_in_kernel_and_in_fallback():
    image, target = images(19, 16, seed=35)
    mask = make_mask("soft", 19, 16)
    x = image.clone().requires_grad_(True)
    ssim_l1(x, target, mask, ssim_weight=-0.2, l1_weight=0.8).backward()
    x_apart = image.clone().requires_grad_(True)
    (ssim(x_apart, target, mask, weight=-0.2) + l1(x_apart, target, mask, weight=0.8)).backward()
    assert torch.equal(x.grad, x_apart.grad)
    y = target.clone().requires_grad_(True)  # a target with gradient: the fallback
    fallback = ssim_l1(image, y, mask, ssim_weight=-0.2, l1_weight=0.8)
    assert fallback.grad_fn is not None
    expected = -0.2 * ssim(image, target, mask).item() + 0.8 * l1(image, target, mask).item()
    assert fallback.item() == pytest.approx(expected, rel=1e-12)


def pixel_case(h=23, w=19, c=3, count=150, dtype=torch.float64, seed=41):
    """Values at listed pixels (repeats included) near a target image with a hole of no
    data (all-zero pixels) and a soft mask."""
    g = torch.Generator().manual_seed(seed)
    target = torch.nn.functional.normalize(
        torch.randn(h, w, c, generator=g, dtype=torch.float64), dim=-1
    )
    target[:3] = 0  # no data in the first rows
    mask = torch.rand(h, w, generator=g, dtype=torch.float64)
    mask[5:7] = 0
    pixels = torch.randint(0, h * w, (count,), generator=g)
    values = target.reshape(-1, c)[pixels] + 0.3 * torch.randn(
        count, c, generator=g, dtype=torch.float64
    )
    values[0] = target.reshape(-1, c)[pixels[0]]  # a zero difference: subgradient 0
    return values.to(dtype), pixels, target.to(dtype), mask.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("weight", [1.0, 0.1, -2.0])
def test_pixel_l1_matches_the_reference_and_its_subgradient(dtype, weight):
    values, pixels, target, mask = pixel_case(dtype=dtype)
    x = values.clone().requires_grad_(True)
    value = masked_pixel_l1(x, pixels, target, mask, weight=weight)
    (value + 0.5).backward()  # an incoming gradient of exactly 1
    x_ref = values.double().clone().requires_grad_(True)
    (weight * ref.masked_pixel_l1(x_ref, pixels, target.double(), mask.double())).backward()
    tolerance = 1e-12 if dtype == torch.float64 else 1e-6
    assert value.item() == pytest.approx(
        weight
        * ref.masked_pixel_l1(values.double(), pixels, target.double(), mask.double()).item(),
        rel=tolerance,
    )
    assert (x.grad.double() - x_ref.grad).abs().max().item() <= tolerance * abs(weight)
    assert x.grad[0].abs().max().item() == 0  # sign(0) = 0
    no_data = (target.reshape(-1, 3)[pixels].abs().sum(-1) == 0) | (mask.reshape(-1)[pixels] == 0)
    assert no_data.any() and x.grad[no_data].abs().max().item() == 0
    x2 = values.clone().requires_grad_(True)
    (3 * masked_pixel_l1(x2, pixels, target, mask, weight=weight)).backward()
    assert torch.allclose(x2.grad, 3 * x.grad, rtol=1e-6, atol=0)


def test_pixel_l1_edge_cases_and_thread_counts(monkeypatch):
    values, pixels, target, mask = pixel_case(count=30_000, h=200, w=180, seed=43)
    runs = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("URHEAD_NUM_THREADS", threads)
        x = values.clone().requires_grad_(True)
        value = masked_pixel_l1(x, pixels, target, mask)
        value.backward()
        runs.append((value.item(), x.grad))
    assert all(v == runs[0][0] and torch.equal(g, runs[0][1]) for v, g in runs)
    # no entry with weight: 0 and no gradient; no entries at all: 0
    x = values[:5].clone().requires_grad_(True)
    zero = masked_pixel_l1(x, pixels[:5], target, torch.zeros_like(mask))
    zero.backward()
    assert zero.item() == 0 and x.grad.abs().max().item() == 0
    empty = masked_pixel_l1(values[:0], pixels[:0], target, mask)
    assert empty.item() == 0
    # a bool mask is the float one
    bool_mask = mask > 0.5
    assert masked_pixel_l1(values, pixels, target, bool_mask).item() == pytest.approx(
        ref.masked_pixel_l1(values, pixels, target, bool_mask.double()).item(), rel=1e-12
    )


def test_pixel_l1_refuses_bad_inputs_by_name():
    values, pixels, target, mask = pixel_case()
    with pytest.raises(IndexRangeError, match="pixels"):
        masked_pixel_l1(values, pixels.clone().fill_(23 * 19), target, mask)
    with pytest.raises(IndexRangeError, match="pixels"):
        masked_pixel_l1(values, -pixels - 1, target, mask)
    with pytest.raises(ShapeError, match="values"):
        masked_pixel_l1(values[:-1], pixels, target, mask)
    with pytest.raises(ShapeError, match="target"):
        masked_pixel_l1(values, pixels, target[..., :2].contiguous(), mask)
    with pytest.raises(ShapeError, match="target"):
        masked_pixel_l1(values, pixels, target, mask[:-1].contiguous())
    with pytest.raises(DTypeError):
        masked_pixel_l1(values, pixels, target.float(), mask)
    for weight in (float("nan"), float("inf"), True, None):
        with pytest.raises(InvalidArgumentError, match="weight"):
            masked_pixel_l1(values, pixels, target, mask, weight=weight)
    with pytest.raises(InvalidArgumentError, match="target"):
        masked_pixel_l1(values, pixels, target.clone().requires_grad_(True), mask)


def test_pixel_l1_passes_non_finite_values_on_as_a_non_finite_loss():
    """A NaN or infinite value (a diverged step) gives a non-finite loss, as the torch ops
    did, for the step guard to reject; it neither raises nor crashes."""
    values, pixels, target, mask = pixel_case(seed=47)
    weighted = (target.reshape(-1, 3)[pixels].abs().sum(-1) > 0) & (mask.reshape(-1)[pixels] > 0)
    entry = int(weighted.nonzero()[0])
    for bad in (float("nan"), float("inf")):
        x = values.clone()
        x[entry, 1] = bad
        value = masked_pixel_l1(x.requires_grad_(True), pixels, target, mask)
        assert not torch.isfinite(value)
        value.backward()


def test_ssim_l1_and_pixel_l1_gradients_match_finite_differences():
    """float64 central differences (NUMERICS.md, how to test) of the one-pass SSIM + L1 and
    of the pixel L1, away from the L1's kinks (no residual within 1e-3 of zero)."""
    image, target = images(9, 8, seed=51)
    target = torch.where((image - target).abs() < 1e-3, target + 2e-3, target)
    mask = make_mask("soft", 9, 8)

    def both(x):
        return masked_ssim_l1(x, target, mask, ssim_weight=-0.2, l1_weight=0.8)

    assert torch.autograd.gradcheck(
        both, (image.clone().requires_grad_(True),), eps=1e-6, atol=1e-7
    )
    values, pixels, target_image, pixel_mask = pixel_case(count=40, seed=53)
    gt = target_image.reshape(-1, 3)[pixels]
    values = torch.where((values - gt).abs() < 1e-3, values + 2e-3, values)

    def pixel(v):
        return masked_pixel_l1(v, pixels, target_image, pixel_mask, weight=0.3)

    assert torch.autograd.gradcheck(
        pixel, (values.clone().requires_grad_(True),), eps=1e-6, atol=1e-7
    )
