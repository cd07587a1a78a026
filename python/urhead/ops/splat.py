"""Differentiable 3D Gaussian splatting with mesh-depth occlusion (Rust forward and
hand-written adjoint), and the normal → quaternion map for surface-aligned Gaussians.

The contract is gsplat's classic rasterization: EWA projection with the clamped Jacobian,
a 0.3 px² dilation, an opacity-aware cut-off radius, 16×16 tiles in (depth, index) order,
α = min(0.99, o·exp(−σ)), samples with α < 1/255 skipped, a stop before T would fall
below 1e-4, and T·background added last. URHead's addition: a sample whose Gaussian depth
(view-space z of its mean) exceeds ``depth_map + depth_eps`` at that pixel is skipped.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from urhead._threads import num_threads
from urhead.camera import Camera
from urhead.errors import DTypeError, InvalidArgumentError, ShapeError
from urhead.ops._bridge import (
    check_camera,
    float_dtype,
    from_numpy,
    grad_to_numpy,
    native,
    to_numpy,
)


class SplatOutput(NamedTuple):
    image: torch.Tensor
    """(H, W, C) composited colour, including T·background."""
    transmittance: torch.Tensor
    """(H, W) transmittance left after the Gaussians (differentiable): what the mesh
    colour behind them is weighted by."""
    means2d: torch.Tensor
    """(N, 2) projected means in pixels. A graph node between projection and compositing,
    like gsplat's: call ``means2d.retain_grad()`` before ``backward()`` and its ``.grad``
    is the screen-space positional gradient densification accumulates."""
    radii: torch.Tensor
    """(N, 2) int32 screen extent in pixels along x and y; (0, 0) for culled Gaussians."""
    visible: torch.Tensor
    """(N,) bool: not culled (in front of the near plane, on screen, non-degenerate)."""
    depths: torch.Tensor
    """(N,) view-space z of the means (zero where culled); no gradient."""


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, sh_degree, camera_args):
        dtype = means.dtype
        args = [
            to_numpy("means", means, dtype),
            to_numpy("quats", quats, dtype),
            to_numpy("scales", scales, dtype),
            to_numpy("opacities", opacities, dtype),
            None if sh is None else to_numpy("sh", sh, dtype),
        ]
        means2d, conics, depths, radii, colors = native("splat_project_forward")(
            *args, sh_degree, camera_args, num_threads()
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(means, quats, scales, opacities, sh)
        ctx.sh_degree = sh_degree
        ctx.camera_args = camera_args
        depths_t, radii_t = torch.from_numpy(depths), torch.from_numpy(radii)
        ctx.mark_non_differentiable(depths_t, radii_t)
        colors_t = from_numpy(colors)
        if colors_t is None:
            colors_t = torch.empty(0, dtype=dtype)
        return torch.from_numpy(means2d), torch.from_numpy(conics), depths_t, radii_t, colors_t

    @staticmethod
    def backward(ctx, v_means2d, v_conics, _v_depths, _v_radii, v_colors):
        means, quats, scales, opacities, sh = ctx.saved_tensors
        dtype = means.dtype
        need = ctx.needs_input_grad
        needs = (need[0], need[1], need[2], sh is not None and need[4])
        if not any(needs):
            return (None,) * 7
        grads = native("splat_project_backward")(
            means.detach().numpy(),
            quats.detach().numpy(),
            scales.detach().numpy(),
            opacities.detach().numpy(),
            None if sh is None else sh.detach().numpy(),
            ctx.sh_degree,
            ctx.camera_args,
            grad_to_numpy("v_means2d", v_means2d, dtype),
            grad_to_numpy("v_conics", v_conics, dtype),
            None if sh is None else grad_to_numpy("v_colors", v_colors, dtype),
            needs,
            num_threads(),
        )
        v_means, v_quats, v_scales, v_sh = map(from_numpy, grads)
        return v_means, v_quats, v_scales, None, v_sh, None, None


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, means2d, conics, colors, opacities, depths, radii, background, depth_map, eps, size
    ):
        dtype = means2d.dtype
        width, height = size
        args = [
            to_numpy("means2d", means2d, dtype),
            to_numpy("conics", conics, dtype),
            to_numpy("colors", colors, dtype),
            to_numpy("opacities", opacities, dtype),
            to_numpy("depths", depths, dtype),
            to_numpy("radii", radii, torch.int32),
            None if background is None else to_numpy("background", background, dtype),
            None if depth_map is None else to_numpy("depth_map", depth_map, dtype),
            eps,
            width,
            height,
        ]
        image, transmittance, state, _pairs = native("splat_rasterize_forward")(
            *args, num_threads()
        )
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(means2d, conics, colors, opacities, depths, radii, background)
        ctx.depth_map = depth_map
        ctx.state = state
        ctx.eps = eps
        ctx.size = size
        t = torch.from_numpy(transmittance)
        ctx.transmittance = t
        return torch.from_numpy(image), t

    @staticmethod
    def backward(ctx, v_image, v_transmittance):
        means2d, conics, colors, opacities, depths, radii, background = ctx.saved_tensors
        dtype = means2d.dtype
        need = ctx.needs_input_grad
        if not any(need[:4]) and not need[6]:
            return (None,) * 10
        width, height = ctx.size
        grads = native("splat_rasterize_backward")(
            ctx.state,
            means2d.detach().numpy(),
            conics.detach().numpy(),
            colors.detach().numpy(),
            opacities.detach().numpy(),
            depths.numpy(),
            radii.numpy(),
            None if background is None else background.detach().numpy(),
            None if ctx.depth_map is None else ctx.depth_map.numpy(),
            ctx.eps,
            width,
            height,
            grad_to_numpy("v_image", v_image, dtype),
            grad_to_numpy("v_transmittance", v_transmittance, dtype),
            ctx.transmittance.numpy() if background is not None and background.dim() == 3 else None,
            num_threads(),
        )
        v_means2d, v_conics, v_colors, v_opacities, v_behind = map(from_numpy, grads)
        v_background = None
        if need[6] and v_image is not None:
            if background.dim() == 3:  # an image behind: T·v_image per pixel, from the kernel
                v_background = v_behind
            else:  # image = … + T·background: ∂L/∂background = Σ_pixels T·v_image.
                t = ctx.transmittance
                v_background = (t[..., None] * v_image).sum((0, 1))
        return (
            v_means2d,
            v_conics,
            v_colors,
            v_opacities,
            None,
            None,
            v_background,
            None,
            None,
            None,
        )


def _check_like(name: str, t: torch.Tensor, dtype: torch.dtype, shape: tuple) -> None:
    if not isinstance(t, torch.Tensor):
        raise DTypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dtype != dtype:
        raise DTypeError(f"{name} must be {dtype} like means, got {t.dtype}")
    if tuple(t.shape) != shape:
        raise ShapeError(f"{name} must be {shape}, got {tuple(t.shape)}")


def rasterize_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    depth_map: torch.Tensor | None = None,
    depth_eps: float = 0.01,
    sh_degree: int | None = None,
) -> SplatOutput:
    """Renders 3D Gaussians with occlusion against a mesh depth map.

    Args:
        means: (N, 3) world-space centres.
        quats: (N, 4) rotations as (w, x, y, z); normalised inside (gradient through the
            normalisation); zero quaternions are culled.
        scales: (N, 3) standard deviations along the local axes (not log-scales); zero or
            subnormal ones are culled.
        opacities: (N,) in [0, 1] (post-sigmoid); below 1/255 culled.
        colors: (N, C) colours/features with any C ≥ 1, or (N, K, 3) spherical-harmonics
            coefficients (3DGS layout and constants, colour = max(SH(dir) + 0.5, 0) with
            dir = normalise(mean − camera centre)).
        camera: the :class:`urhead.Camera`.
        background: what shows through the Gaussians, added as T·background: a (C,)
            colour, or an (H, W, S) image with S ≥ C whose first C channels show (a
            mesh's RGBA: the Gaussians composited over it in the same pass, as
            :func:`urhead.ops.composite` would, without its pass over three images; its
            values are data, so a non-finite one passes into its pixel). Zeros when None.
            Differentiable (an image's gradient is T·v_image, zero past its C channels).
        depth_map: (H, W) linear view-space depth of the mesh (+inf where there is none);
            a sample whose Gaussian depth exceeds ``depth_map + depth_eps`` at that pixel is
            skipped. No gradient flows to it (the test is discrete).
        depth_eps: occlusion tolerance in scene units.
        sh_degree: degree 0–3 used from (N, K, 3) SH; default the largest K allows.

    Returns:
        :class:`SplatOutput` ``(image, transmittance, means2d, radii, visible, depths)``.

    Gradients flow to ``means``, ``quats``, ``scales``, ``opacities``, ``colors`` (or SH)
    and ``background``. Where α = min(0.99, o·g) clamps, α passes no gradient (the exact
    derivative of the min, as in gsplat). Inputs: float32 or float64 (all alike),
    contiguous, CPU. Threads: ``URHEAD_NUM_THREADS`` or ``torch.get_num_threads()``.
    """
    dtype = float_dtype("means", means)
    check_camera(camera)
    if means.dim() != 2 or means.shape[1] != 3:
        raise ShapeError(f"means must be (N, 3), got {tuple(means.shape)}")
    n = means.shape[0]
    _check_like("quats", quats, dtype, (n, 4))
    _check_like("scales", scales, dtype, (n, 3))
    _check_like("opacities", opacities, dtype, (n,))
    if not isinstance(colors, torch.Tensor) or colors.dtype != dtype:
        raise DTypeError(f"colors must be a {dtype} tensor like means")
    if colors.dim() == 3:
        if colors.shape[0] != n or colors.shape[2] != 3:
            raise ShapeError(f"sh colors must be (N, K, 3) with N = {n}, got {tuple(colors.shape)}")
        k = colors.shape[1]
        max_degree = math.isqrt(k) - 1 if k > 0 else -1
        degree = max_degree if sh_degree is None else int(sh_degree)
        if not 0 <= degree <= 3 or (degree + 1) ** 2 > k:
            raise InvalidArgumentError(
                f"sh_degree must be in [0, 3] with (sh_degree + 1)² ≤ K = {k}, got {degree}"
            )
        sh = colors
    elif colors.dim() == 2:
        if colors.shape[0] != n:
            raise ShapeError(f"colors must be (N, C) with N = {n}, got {tuple(colors.shape)}")
        if sh_degree is not None:
            raise InvalidArgumentError("sh_degree is only meaningful with (N, K, 3) SH colours")
        sh, degree = None, 0
    else:
        raise ShapeError(f"colors must be (N, C) or (N, K, 3), got {tuple(colors.shape)}")
    channels = 3 if sh is not None else colors.shape[1]
    if background is not None and isinstance(background, torch.Tensor) and background.dim() == 3:
        behind = tuple(background.shape)
        if behind[:2] != (camera.height, camera.width) or behind[2] < channels:
            raise ShapeError(
                f"background must be (C,) = ({channels},) or (H, W, S) = ({camera.height}, "
                f"{camera.width}, S ≥ {channels}), got {behind}"
            )
        _check_like("background", background, dtype, behind)
        background = background.contiguous()
    elif background is not None:
        _check_like("background", background, dtype, (channels,))
    if depth_map is not None:
        _check_like("depth_map", depth_map, dtype, (camera.height, camera.width))
        depth_map = depth_map.detach()
    eps = float(depth_eps)
    if not math.isfinite(eps):
        raise InvalidArgumentError(f"depth_eps must be finite, got {depth_eps}")

    means2d, conics, depths, radii, sh_colors = _Project.apply(
        means, quats, scales, opacities, sh, degree, camera.core_args()
    )
    rgb = sh_colors if sh is not None else colors
    image, transmittance = _Rasterize.apply(
        means2d,
        conics,
        rgb,
        opacities,
        depths,
        radii,
        background,
        depth_map,
        eps,
        (camera.width, camera.height),
    )
    visible = (radii > 0).all(-1)
    return SplatOutput(image, transmittance, means2d, radii, visible, depths)


def normal_to_quat(normals: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (w, x, y, z) whose local z axis (a Gaussian's thin axis when
    ``scales[:, 2]`` is the smallest) points along each normal.

    Args:
        normals: (N, 3), any length; normalised inside (gradient through it).

    Returns:
        (N, 4) unit quaternions.

    The frame is the branchless orthonormal basis of Duff et al. (2017): for n_z ≥ 0 the
    shortest-arc rotation from +z, q = (1 + n_z, −n_y, n_x, 0)/√(2(1 + n_z)); for n_z < 0
    the shortest arc from −z followed by a half-turn about x, q = (−n_y, 1 − n_z, 0, n_x)/
    √(2(1 − n_z)). Both denominators are ≥ √2, so values and gradients are bounded for
    every direction; the in-plane (tangent) axes flip across n_z = 0, which matters only
    for in-plane-anisotropic Gaussians crossing that plane. Inputs are scaled by their
    largest component before normalising, so tiny (1e-30) and huge (1e30) normals work.
    Fallback: zero or non-finite normals give the identity (1, 0, 0, 0) with zero gradient.
    Plain torch (cheap and stable, so autograd differentiates it).
    """
    if not isinstance(normals, torch.Tensor) or not normals.is_floating_point():
        raise DTypeError("normals must be a float tensor")
    if normals.dim() != 2 or normals.shape[1] != 3:
        raise ShapeError(f"normals must be (N, 3), got {tuple(normals.shape)}")
    finite = torch.isfinite(normals).all(-1)
    safe = torch.where(finite[:, None], normals, torch.zeros_like(normals))
    peak = safe.abs().amax(-1, keepdim=True)
    valid = finite & (peak[:, 0] > 0)
    fallback = torch.tensor([0.0, 0.0, 1.0], dtype=normals.dtype, device=normals.device)
    scaled = torch.where(valid[:, None], safe / torch.where(peak > 0, peak, 1.0), fallback)
    n = scaled / scaled.norm(dim=-1, keepdim=True)
    nx, ny, nz = n.unbind(-1)
    up = nz >= 0
    one = torch.ones_like(nz)
    zero = torch.zeros_like(nz)
    # Each branch's denominator sees n_z only where that branch is taken (torch.where rather
    # than a clamp, whose gradient vanishes at n_z = 0 exactly: the up branch's derivative
    # there is the one-sided derivative from n_z > 0, as urhead-core's lift computes it).
    nz_up, nz_down = torch.where(up, nz, zero), torch.where(up, zero, nz)
    q_up = torch.stack([1 + nz, -ny, nx, zero], -1) / torch.sqrt(2 * (1 + nz_up))[:, None]
    q_down = torch.stack([-ny, 1 - nz, zero, nx], -1) / torch.sqrt(2 * (1 - nz_down))[:, None]
    q = torch.where(up[:, None], q_up, q_down)
    identity = torch.stack([one, zero, zero, zero], -1)
    return torch.where(valid[:, None], q, identity)
