"""LBS forward+backward at FLAME size (5023 vertices, 400 betas, 5 joints), urhead vs the
plain-torch reference, medians in one run. Usage: python benchmarks/bench_lbs.py"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))

from conftest import make_skinned_model
from timing import median_ms, report
from urhead._threads import num_threads
from urhead.ops import _reference, lbs


def case(fn, model, batch):
    g = torch.Generator().manual_seed(0)
    betas = torch.randn(batch, 400, generator=g).requires_grad_()
    pose = (torch.randn(batch, 15, generator=g) * 0.3).requires_grad_()
    transl = torch.randn(batch, 3, generator=g).requires_grad_()
    weights = torch.randn(batch, 5023, 3, generator=g)

    def forward():
        with torch.no_grad():
            fn(betas, pose, *model.tables(), transl=transl)

    def forward_backward():
        out = fn(betas, pose, *model.tables(), transl=transl)
        torch.autograd.grad((out.verts * weights).sum(), (betas, pose, transl))

    return forward, forward_backward


def measure(batches=(1, 16), repeats: int = 30) -> list[tuple[str, float, float]]:
    """``(case, urhead ms, torch-reference ms)`` medians, forward and forward+backward."""
    model = make_skinned_model(num_verts=5023, num_betas=400, dtype=torch.float32)
    rows = []
    for batch in batches:
        ours_f, ours_fb = case(lbs, model, batch)
        ref_f, ref_fb = case(_reference.lbs, model, batch)
        rows.append((f"forward B={batch}", median_ms(ours_f, repeats), median_ms(ref_f, repeats)))
        rows.append(
            (
                f"forward+backward B={batch}",
                median_ms(ours_fb, repeats),
                median_ms(ref_fb, repeats),
            )
        )
    return rows


def main():
    print(f"LBS at FLAME size, float32, {num_threads()} threads")
    report(measure())


if __name__ == "__main__":
    main()
