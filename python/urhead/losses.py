"""Training losses and image metrics of the paper (Sec. "Training Objectives"), masked:
every term is averaged inside the head mask, so background pixels neither train nor score.

Images are (H, W, C) float tensors in [0, 1]; masks are (H, W) in [0, 1] or bool.
:func:`ssim` and :func:`l1` run the fused Rust kernels of :mod:`urhead.ops.ssim` for CPU
float32/float64 images with a constant target and mask (the training loop's case) and fall
back to plain torch otherwise; :func:`ssim_map` stays plain torch, the kernels' reference.
"""

from __future__ import annotations

from functools import lru_cache

import torch
import torch.nn.functional as F

from urhead.ops.ssim import l1_loss, ssim_loss

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


@lru_cache(maxsize=4)
def _gaussian_window(dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    w = torch.exp(-(x**2) / (2 * SSIM_SIGMA**2))
    return (w / w.sum()).to(dtype)


def _blur(x: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of (N, H, W) with zero padding (the 3DGS convention)."""
    w = _gaussian_window(x.dtype)
    x = x[:, None]
    x = F.conv2d(x, w.view(1, 1, -1, 1), padding=(SSIM_WINDOW // 2, 0))
    x = F.conv2d(x, w.view(1, 1, 1, -1), padding=(0, SSIM_WINDOW // 2))
    return x[:, 0]


def ssim_map(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM (H, W) of (H, W, C) images (mean over channels), Gaussian window
    11 × 11, σ = 1.5, C1 = 0.01², C2 = 0.03² (Wang et al. 2004, as in 3DGS)."""
    x = image.permute(2, 0, 1)
    y = target.permute(2, 0, 1)
    mu_x, mu_y = _blur(x), _blur(y)
    var_x = _blur(x * x) - mu_x**2
    var_y = _blur(y * y) - mu_y**2
    cov = _blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (num / den).mean(0)


def _masked_mean(values: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return values.mean()
    weight = mask.to(values.dtype)
    if values.dim() == 3:
        weight = weight[..., None].expand_as(values)
    return (values * weight).sum() / weight.sum().clamp_min(1)


def _kernel_applies(image, target, mask) -> bool:
    """Whether the Rust kernels take these inputs: CPU (H, W, C) float32/float64 of one dtype,
    differentiated in ``image`` only."""
    tensors = [image, target] + ([] if mask is None else [mask])
    return (
        all(isinstance(t, torch.Tensor) and t.device.type == "cpu" for t in tensors)
        and image.dtype in (torch.float32, torch.float64)
        and target.dtype == image.dtype
        and image.dim() == 3
        and not target.requires_grad
        and not (mask is not None and mask.requires_grad)
    )


def ssim(image, target, mask=None) -> torch.Tensor:
    """Mean SSIM inside ``mask``."""
    if _kernel_applies(image, target, mask):
        mask = None if mask is None else mask.contiguous()
        return ssim_loss(image.contiguous(), target.contiguous(), mask)
    return _masked_mean(ssim_map(image, target), mask)


def l1(image, target, mask=None) -> torch.Tensor:
    """Mean absolute error inside ``mask``."""
    if _kernel_applies(image, target, mask):
        mask = None if mask is None else mask.contiguous()
        return l1_loss(image.contiguous(), target.contiguous(), mask)
    return _masked_mean((image - target).abs(), mask)


def psnr(image, target, mask=None) -> torch.Tensor:
    """PSNR in dB of [0, 1] images, from the MSE inside ``mask``."""
    mse = _masked_mean((image - target) ** 2, mask)
    return -10 * torch.log10(mse.clamp_min(1e-20))


def uniform_laplacian(faces: torch.Tensor, num_verts: int) -> torch.Tensor:
    """Sparse (V, V) operator L with (L v)_i = v_i − mean of i's edge neighbours.
    Isolated vertices get a zero row."""
    f = faces.long()
    edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges = torch.cat([edges, edges.flip(1)]).unique(dim=0)
    degree = torch.bincount(edges[:, 0], minlength=num_verts).to(torch.float32)
    rows = torch.cat([edges[:, 0], torch.arange(num_verts)])
    cols = torch.cat([edges[:, 1], torch.arange(num_verts)])
    has_neighbours = (degree > 0).to(torch.float32)
    values = torch.cat([-1 / degree[edges[:, 0]], has_neighbours])
    return torch.sparse_coo_tensor(
        torch.stack([rows, cols]), values, (num_verts, num_verts), check_invariants=True
    ).coalesce()


def laplacian_loss(verts: torch.Tensor, laplacian: torch.Tensor) -> torch.Tensor:
    """(1/V) Σ_i ‖δ_i‖² for (V, 3) or (B, V, 3) vertices (the paper's L_lap)."""
    flat = verts.reshape(-1, verts.shape[-2], 3)
    deltas = torch.stack([laplacian.to(v.dtype) @ v for v in flat])
    return (deltas**2).sum(-1).mean()
