"""Each kernel's forward+backward median next to its plain-torch reference, same run."""

from __future__ import annotations

from pathlib import Path

import torch

import bench_adam
import bench_lbs
import bench_raster
import bench_splat
import urhead
from sections.common import ms, ratio, save, table
from timing import median_ms

TITLE = "Kernels: forward + backward against the plain-torch reference"


def _row(kernel, size, ours, reference, note=""):
    return dict(kernel=kernel, size=size, urhead_ms=ours, torch_ms=reference, note=note)


def lbs_rows(quick: bool) -> list[dict]:
    batches = (1,) if quick else (1, 16)
    rows = []
    for name, ours, ref in bench_lbs.measure(batches, repeats=10 if quick else 30):
        if name.startswith("forward+backward"):
            batch = name.split("B=")[1]
            size = f"FLAME: 5023 v, 400 betas, 5 joints, B = {batch}"
            rows.append(_row("lbs", size, ours, ref))
    return rows


def mesh_rows(quick: bool) -> list[dict]:
    """Full size: urhead only (the brute-force reference would take minutes). Reduced
    scene: both, so the ratio is measured, not extrapolated."""
    full = bench_raster.Scene(70, 72, 512, 2048)
    full_ms = bench_raster.measure_ops(full, bench_raster.Rust, 2 if quick else 5)
    small_args = (12, 13, 64, 256) if quick else (20, 21, 128, 512)
    small = bench_raster.Scene(*small_args, seed=1)
    ours = bench_raster.measure_ops(small, bench_raster.Rust, 5)
    reference = bench_raster.measure_ops(small, bench_raster.Reference, 1)
    faces_full, faces_small = full.faces.shape[0], small.faces.shape[0]
    side = small_args[2]
    rows = []
    for op in (*bench_raster.OPS, "chain"):
        label = "mesh chain (4 ops + shading)" if op == "chain" else op
        rows.append(_row(label, f"512², {faces_full} faces, 2048² × 56 texture", full_ms[op], None))
        rows.append(
            _row(
                label,
                f"{side}², {faces_small} faces, {small_args[3]}² × 56 texture",
                ours[op],
                reference[op],
                "reference: brute force (every triangle at every pixel)"
                if op in ("rasterize", "chain")
                else "",
            )
        )
    return rows


def splat_rows(quick: bool) -> list[dict]:
    n = 30_000
    r = bench_splat.bench(n, reps=5 if quick else 15, torch_max=3_000 if quick else n)
    note = "reference: plain-torch 16×16 tile rasterizer, autograd backward"
    if r["torch_n"] != n:
        note += f"; run on {r['torch_n']} Gaussians, scaled per tile-list pair"
    size = f"{n} head-sized Gaussians, 512², SH degree 3"
    return [_row("splatting: project + rasterize", size, r["fwd_bwd"], r["torch_fwd_bwd"], note)]


def adam_rows(quick: bool) -> list[dict]:
    touched = (20_000,) if quick else (20_000, 100_000)
    sparse, dense_ms = bench_adam.measure(touched, dense_repeats=2 if quick else 5)
    size = f"{bench_adam.SIDE}² × {bench_adam.CHANNELS} atlas"
    return [
        _row(
            f"sparse Adam step ({name.split('(')[1].split(')')[0]})",
            f"{size}, {name.split(', ')[1]}",
            ours,
            dense_ms,
            "reference: dense torch.optim.Adam step over the whole atlas",
        )
        for name, ours in sparse
    ]


def ssim_rows(quick: bool) -> list[dict]:
    """SSIM forward + backward; reference: the plain-torch masked SSIM of
    ``urhead.ops._reference`` (``urhead.losses.ssim`` itself runs the Rust op)."""
    from urhead import ops
    from urhead.ops import _reference

    g = torch.Generator().manual_seed(0)
    image = torch.rand(512, 512, 3, generator=g)
    target = torch.rand(512, 512, 3, generator=g)

    def fwd_bwd(fn):
        x = image.clone().requires_grad_(True)
        fn(x, target).backward()

    repeats = 5 if quick else 15
    ours = median_ms(lambda: fwd_bwd(ops.masked_ssim), repeats)
    ref = median_ms(lambda: fwd_bwd(_reference.masked_ssim), repeats)
    note = "reference: plain-torch SSIM map (separable conv2d), masked mean"
    return [_row("masked_ssim", "512² × 3", ours, ref, note)]


def run(quick: bool) -> dict:
    rows = lbs_rows(quick) + mesh_rows(quick) + splat_rows(quick)
    rows += adam_rows(quick) + ssim_rows(quick) + shading_rows(quick)
    return {"rows": rows, "urhead_version": getattr(urhead, "__version__", "unknown")}


def shading_rows(quick: bool) -> list[dict]:
    """SH shading of an iteration's covered pixels (rows of the packed 56-channel samples,
    degree 3) vs the plain-torch reference."""
    from urhead import ops
    from urhead.ops import _reference

    g = torch.Generator().manual_seed(0)
    rows = torch.rand(90_000, 56, generator=g) - 0.5
    dirs = torch.nn.functional.normalize(torch.randn(90_000, 3, generator=g), dim=-1)
    weights = torch.rand(90_000, 3, generator=g)

    def fwd_bwd(fn):
        x = rows.clone().requires_grad_(True)
        (fn(x, dirs, 3) * weights).sum().backward()

    repeats = 5 if quick else 15
    ours = median_ms(lambda: fwd_bwd(ops.sh_shade), repeats)
    ref = median_ms(lambda: fwd_bwd(_reference.sh_shade), repeats)
    note = "reference: plain-torch basis × coefficients, autograd backward"
    return [_row("sh_shade", "90k samples × 56 channels, degree 3", ours, ref, note)]


def render(results: dict, figures: Path) -> str:
    rows = results["rows"]
    body = table(
        ["kernel", "size", "urhead ms", "torch ms", "speed-up", "note"],
        [
            [
                r["kernel"],
                r["size"],
                ms(r["urhead_ms"]),
                ms(r["torch_ms"]),
                ratio(r["torch_ms"], r["urhead_ms"]),
                r["note"],
            ]
            for r in rows
        ],
    )
    compared = [r for r in rows if r["torch_ms"]]
    figure = ""
    if compared:
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 0.4 * len(compared) + 1))
        labels = [f"{r['kernel']} ({r['size'].split(',')[0]})" for r in compared]
        speedups = [r["torch_ms"] / r["urhead_ms"] for r in compared]
        ax.barh(range(len(compared)), speedups, color="#4477aa")
        ax.set_yticks(range(len(compared)), labels, fontsize=8)
        ax.invert_yaxis()
        ax.set_xscale("log")
        ax.axvline(1, color="black", lw=0.8)
        ax.set_xlabel("speed-up over the plain-torch reference (forward + backward, log)")
        figure = save(fig, figures, "kernels_speedup")
    return "\n\n".join(
        [
            "Medians of forward + backward (one optimiser step for Adam), float32. The torch "
            "column is the plain-torch reference (`urhead.ops._reference`, autograd backward) "
            "timed in the same process on the same inputs; speed-up = torch / urhead. Rows "
            "without a torch figure are sizes the reference cannot run at in reasonable time; "
            "the row below each is a reduced scene where both ran.",
            body,
            figure,
        ]
    )
