"""Benchmark of urhead.ops.rasterize_gaussians against a plain-torch tile rasterizer.

Scene: N Gaussians of head-avatar size (1–5 mm, log-uniform) filling a head-sized
ellipsoid (semi-axes 8, 11, 10 cm) 0.75 m in front of a 512² camera that the head fills to
about 70 %; SH degree 3; white background. Prints, per N: forward and forward+backward
medians, forward-only FPS, ns per evaluated Gaussian-pixel pair (pairs the kernel's tile
loop evaluated: 8 per sampled 8-pixel chunk), and the ratio to a plain-torch tile
rasterizer (same projection, tile lists and compositing rules, autograd backward)
measured in the same run. The torch rasterizer runs on at most ``--torch-max`` Gaussians
(a random subset of the scene); its time is scaled to the full scene per evaluated pair,
which the output says.

Threads: the kernels run on ``--threads`` (``URHEAD_NUM_THREADS``). Torch runs on one
thread throughout: its OpenMP workers spin-wait after each op and then compete with the
kernel pool for the same cores (on the 2-core machine that alone doubled the measured
forward+backward), and the plain-torch rasterizer's many small per-tile ops were slower
on two OpenMP threads than on one.

    python benchmarks/bench_splat.py [--sizes 10000 30000 100000] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch

import urhead
from urhead import _core
from urhead.ops import _reference as ref
from urhead.ops import rasterize_gaussians

sys.path.insert(0, os.path.dirname(__file__))
from timing import median_ms

SIZE = 512
TILE = 16


def head_scene(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    p = torch.empty(0, 3, dtype=torch.float64)
    while p.shape[0] < n:
        q = torch.rand(2 * n, 3, generator=g, dtype=torch.float64) * 2 - 1
        p = torch.cat([p, q[(q * q).sum(-1) <= 1]])
    means = p[:n] * torch.tensor([0.08, 0.11, 0.10], dtype=torch.float64)
    means[:, 2] += 0.75
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = 1e-3 * 5 ** torch.rand(n, 3, generator=g, dtype=torch.float64)
    opacities = 0.1 + 0.89 * torch.rand(n, generator=g, dtype=torch.float64)
    sh = torch.randn(n, 16, 3, generator=g, dtype=torch.float64) * 0.2
    sh[:, 0] *= 5
    focal = 0.7 * SIZE * 0.75 / 0.22
    k = torch.tensor([[focal, 0, SIZE / 2], [0, focal, SIZE / 2], [0, 0, 1]])
    cam = urhead.Camera(k, torch.eye(4), SIZE, SIZE)
    return [t.float() for t in (means, quats, scales, opacities, sh)], cam


def torch_tile_rasterize(means2d, conics, colors, opacities, depths, radii, bg):
    """Plain-torch 16×16 tile rasterizer: every Gaussian of a tile's list evaluated at all
    256 pixels, T by cumulative products, the same alpha/stop rules. Returns (image, T,
    evaluated pairs)."""
    tiles = SIZE // TILE
    vis = (radii > 0).all(-1).nonzero()[:, 0]
    vis = vis[torch.sort(depths[vis], stable=True).indices]
    m, r = means2d[vis].detach(), radii[vis].float()
    x0 = ((m[:, 0] - r[:, 0]) / TILE).floor().clamp(0, tiles).long()
    x1 = ((m[:, 0] + r[:, 0]) / TILE).ceil().clamp(0, tiles).long()
    y0 = ((m[:, 1] - r[:, 1]) / TILE).floor().clamp(0, tiles).long()
    y1 = ((m[:, 1] + r[:, 1]) / TILE).ceil().clamp(0, tiles).long()
    lists = [[] for _ in range(tiles * tiles)]
    spans = zip(vis.tolist(), x0.tolist(), x1.tolist(), y0.tolist(), y1.tolist(), strict=True)
    for g, a, b, c, d in spans:
        for ty in range(c, d):
            for tx in range(a, b):
                lists[ty * tiles + tx].append(g)
    offs = torch.arange(TILE, dtype=means2d.dtype) + 0.5
    rows, pairs = [], 0
    for ty in range(tiles):
        row = []
        for tx in range(tiles):
            ids = lists[ty * tiles + tx]
            if not ids:
                row.append(bg.expand(TILE, TILE, 3))
                continue
            pairs += len(ids) * TILE * TILE
            ids = torch.tensor(ids)
            px = (tx * TILE + offs)[None, None, :]
            py = (ty * TILE + offs)[None, :, None]
            mm, cc = means2d[ids], conics[ids]
            dx = mm[:, 0, None, None] - px
            dy = mm[:, 1, None, None] - py
            sigma = 0.5 * (cc[:, 0, None, None] * dx * dx + cc[:, 2, None, None] * dy * dy)
            sigma = sigma + cc[:, 1, None, None] * dx * dy
            alpha = torch.clamp(opacities[ids, None, None] * torch.exp(-sigma), max=0.99)
            alpha = torch.where((alpha >= 1 / 255) & (sigma >= 0), alpha, torch.zeros_like(alpha))
            after = torch.cumprod(1 - alpha, 0)
            before = torch.cat([torch.ones_like(after[:1]), after[:-1]])
            keep = after >= 1e-4
            w = alpha * before * keep
            t_final = torch.where(keep, after, torch.ones_like(after)).amin(0)
            row.append((w[..., None] * colors[ids, None, None, :]).sum(0) + t_final[..., None] * bg)
        rows.append(torch.cat(row, 1))
    return torch.cat(rows, 0), pairs


def loss_of(image, transmittance):
    return image.sum() + transmittance.sum()


def bench(n: int, reps: int, torch_max: int):
    (means, quats, scales, opac, sh), cam = head_scene(n)
    bg = torch.ones(3)

    def forward():
        with torch.no_grad():
            rasterize_gaussians(means, quats, scales, opac, sh, cam, bg)

    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, sh)]

    def forward_backward():
        for t in leaves:
            t.grad = None  # as optimizer.zero_grad(set_to_none=True) does in training
        out = rasterize_gaussians(*leaves, cam, bg)
        loss_of(out.image, out.transmittance).backward()

    forward()
    forward_backward()
    fwd = median_ms(forward, repeats=reps, warmup=0, max_seconds=float("inf"))
    fwd_bwd = median_ms(forward_backward, repeats=reps, warmup=0, max_seconds=float("inf"))

    # Pairs the kernel's tile loop evaluated, from one direct call.
    with torch.no_grad():
        m2d, conics, depths, radii, colors = ref.project_gaussians(
            means, quats, scales, opac, cam, sh, 3
        )
    _, _, binning, pairs = _core.splat_rasterize_forward(
        m2d.numpy(),
        conics.numpy(),
        colors.numpy(),
        opac.numpy(),
        depths.numpy(),
        radii.numpy(),
        bg.numpy(),
        None,
        0.01,
        SIZE,
        SIZE,
        urhead._threads.num_threads(),
    )

    # Plain torch on (a subset of) the same scene, timed once each (it is slow).
    k = min(n, torch_max)
    sub = torch.randperm(n, generator=torch.Generator().manual_seed(1))[:k]
    t_leaves = [t[sub].clone().requires_grad_(True) for t in (means, quats, scales, opac, sh)]

    def torch_run(backward: bool):
        with torch.set_grad_enabled(backward):
            m, q, s, o, c = t_leaves
            m2, co, de, ra, col = ref.project_gaussians(m, q, s, o, cam, c, 3)
            image, tp = torch_tile_rasterize(m2, co, col, o, de, ra, bg)
            if backward:
                image.sum().backward()
            return tp

    t0 = time.perf_counter()
    torch_pairs = torch_run(False)
    torch_fwd = 1e3 * (time.perf_counter() - t0)
    t0 = time.perf_counter()
    torch_run(True)
    torch_fwd_bwd = 1e3 * (time.perf_counter() - t0)
    # The torch rasterizer evaluates all 256 pixels of a tile for every Gaussian in its
    # list: scale its time per pair to the full scene's tile-list pairs.
    scale = binning.num_intersections * TILE * TILE / torch_pairs
    return dict(
        n=n,
        fwd=fwd,
        fwd_bwd=fwd_bwd,
        fps=1e3 / fwd,
        ns_pair_fwd=1e6 * fwd / pairs,
        ns_pair_fwd_bwd=1e6 * fwd_bwd / pairs,
        pairs=pairs,
        torch_n=k,
        torch_fwd=torch_fwd * scale,
        torch_fwd_bwd=torch_fwd_bwd * scale,
        torch_pairs=torch_pairs * scale,
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 30_000, 100_000])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--reps", type=int, default=15)
    parser.add_argument("--torch-max", type=int, default=3_000)
    args = parser.parse_args()
    os.environ["URHEAD_NUM_THREADS"] = str(args.threads)
    torch.set_num_threads(1)
    print(
        f"512² image, SH degree 3, {args.threads} kernel threads, 1 torch thread; "
        f"medians of {args.reps} runs"
    )
    for n in args.sizes:
        r = bench(n, args.reps, args.torch_max)
        note = ""
        if r["torch_n"] != n:
            note = f" (ran {r['torch_n']} Gaussians, scaled per tile-list pair)"
        print(
            f"N={n:>6}: forward {r['fwd']:7.2f} ms ({r['fps']:6.1f} FPS), forward+backward "
            f"{r['fwd_bwd']:7.2f} ms | {r['pairs'] / 1e6:6.1f} M pairs, "
            f"{r['ns_pair_fwd']:.2f} ns/pair forward, {r['ns_pair_fwd_bwd']:.2f} ns/pair fwd+bwd"
        )
        print(
            f"          plain torch: forward {r['torch_fwd']:8.0f} ms, forward+backward "
            f"{r['torch_fwd_bwd']:8.0f} ms{note} → ratio {r['torch_fwd'] / r['fwd']:5.0f}× "
            f"forward, {r['torch_fwd_bwd'] / r['fwd_bwd']:5.0f}× forward+backward"
        )


if __name__ == "__main__":
    main()
