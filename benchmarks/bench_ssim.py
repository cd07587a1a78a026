"""The training loop's image-loss stage at 512 × 512 × 3 float32 with a head mask: masked
SSIM and L1, forward and forward + backward, against the plain-torch references measured
in the same run. DESIGN.md budget for the whole SSIM + L1 stage: 10 ms.
Usage: python benchmarks/bench_ssim.py"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))

from timing import median_ms, report
from urhead._threads import num_threads
from urhead.ops import _reference as ref
from urhead.ops import masked_l1, masked_ssim

SIDE, CHANNELS = 512, 3


def inputs():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(SIDE, SIDE, CHANNELS, generator=g)
    image = (target + 0.1 * torch.randn(SIDE, SIDE, CHANNELS, generator=g)).clamp(0, 1)
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, SIDE), torch.linspace(-1, 1, SIDE), indexing="ij")
    mask = (ys / 0.9) ** 2 + (xs / 0.7) ** 2 < 1  # a head-sized ellipse
    return image, target, mask


def stage(ssim_fn, l1_fn, image, target, mask, lam=0.2):
    """λ(1 − SSIM) + (1 − λ)·L1 and its backward, as the trainer evaluates it."""
    image.grad = None
    loss = lam * (1 - ssim_fn(image, target, mask)) + (1 - lam) * l1_fn(image, target, mask)
    loss.backward()


def forward_backward(fn, image, target, mask):
    image.grad = None
    fn(image, target, mask).backward()


def main():
    print(f"{SIDE}² × {CHANNELS} float32, elliptical mask, {num_threads()} threads")
    image, target, mask = inputs()
    leaf = image.clone().requires_grad_(True)
    rows = []
    for name, ours, theirs in (
        ("SSIM", masked_ssim, ref.masked_ssim),
        ("L1", masked_l1, ref.masked_l1),
    ):
        rows.append(
            (
                f"{name} forward",
                median_ms(lambda f=ours: f(image, target, mask)),
                median_ms(lambda f=theirs: f(image, target, mask), repeats=10),
            )
        )
        rows.append(
            (
                f"{name} forward + backward",
                median_ms(lambda f=ours: forward_backward(f, leaf, target, mask)),
                median_ms(lambda f=theirs: forward_backward(f, leaf, target, mask), repeats=10),
            )
        )
    rows.append(
        (
            "SSIM + L1 stage, forward + backward",
            median_ms(lambda: stage(masked_ssim, masked_l1, leaf, target, mask)),
            median_ms(
                lambda: stage(ref.masked_ssim, ref.masked_l1, leaf, target, mask), repeats=10
            ),
        )
    )
    report(rows)


if __name__ == "__main__":
    main()
