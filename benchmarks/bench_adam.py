"""Sparse Adam on a 2048² × 56 UV atlas (the paper's maps), with float32 and with bfloat16
moments, against a dense torch.optim.Adam step over the same table, medians in one run.
Usage: python benchmarks/bench_adam.py"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))

from timing import median_ms, report
from urhead._threads import num_threads
from urhead.optim import SparseAdam

SIDE, CHANNELS = 2048, 56
MOMENTS = ("float32", "bfloat16")


def patch_rows(count: int, generator) -> torch.Tensor:
    """Texels of random 32×32 UV patches: a rendered view touches coherent regions."""
    offsets = (torch.arange(32)[:, None] * SIDE + torch.arange(32)).reshape(-1)
    rows = torch.empty(0, dtype=torch.int64)
    while rows.numel() < count:
        corner = torch.randint(0, SIDE - 32, (2,), generator=generator)
        rows = torch.cat([rows, corner[0] * SIDE + corner[1] + offsets]).unique()
    return rows[:count]


def sparse_timings(
    generator, touched_counts=(20_000, 100_000, 400_000), moments_kinds=MOMENTS
) -> list[tuple[str, float]]:
    """``[(case, ms)]``: one sparse step of each moment storage at each touched count."""
    timings = []
    for moments in moments_kinds:
        param = torch.zeros(SIDE, SIDE, CHANNELS)
        opt = SparseAdam([param], lr=1e-3, moments=moments)
        for touched in touched_counts:
            rows = patch_rows(touched, generator)
            values = torch.randn(touched, CHANNELS, generator=generator)
            index = torch.stack([rows // SIDE, rows % SIDE])
            grad = torch.sparse_coo_tensor(index, values, param.shape).coalesce()

            def step(grad=grad, param=param, opt=opt):
                param.grad = grad
                opt.step()

            case = f"sparse Adam ({moments} moments), {touched} texels touched"
            timings.append((case, median_ms(step)))
        del param, opt  # ~2 GB of float32 tables: freed before the next kind's
    return timings


def measure(touched_counts=(20_000, 100_000, 400_000), dense_repeats: int = 5):
    """``(sparse rows [(case, ms)], dense torch.optim.Adam step ms)``, medians."""
    generator = torch.Generator().manual_seed(0)
    sparse = sparse_timings(generator, touched_counts)
    dense = torch.zeros(SIDE, SIDE, CHANNELS, requires_grad=True)
    dense.grad = torch.randn(SIDE, SIDE, CHANNELS, generator=generator)
    dense_ms = median_ms(torch.optim.Adam([dense], lr=1e-3).step, repeats=dense_repeats, warmup=1)
    return sparse, dense_ms


def main():
    print(f"UV atlas {SIDE}² × {CHANNELS} float32, {num_threads()} threads")
    sparse, dense_ms = measure()
    report([(name, ms, dense_ms) for name, ms in sparse])
    print(f"(torch ms: one dense torch.optim.Adam step over the whole atlas, {dense_ms:.0f} ms)")


if __name__ == "__main__":
    main()
