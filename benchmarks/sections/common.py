"""Shared helpers for sections: number formatting, markdown tables, figure saving, the
trainer's thread setting."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import torch


@contextmanager
def one_torch_thread():
    """torch on one thread inside the block, as the trainer and the renderer run it
    (``urhead._threads.configure_threads``): urhead's kernels take the cores. The report's
    own torch thread count, which the plain-torch references use, is restored after."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def ms(x: float | None) -> str:
    if x is None:
        return "—"
    return f"{x:.3g}" if x < 100 else f"{x:.0f}"


def ratio(reference: float | None, ours: float | None) -> str:
    if not reference or not ours:
        return "—"
    r = reference / ours
    return f"{r:.2g}×" if r < 10 else f"{r:.0f}×"


def table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def save(fig, figures: Path, name: str) -> str:
    """Saves ``fig`` as figures/name.png; returns the markdown image link (from docs/)."""
    import matplotlib.pyplot as plt

    figures.mkdir(parents=True, exist_ok=True)
    fig.savefig(figures / f"{name}.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return f"![{name}](benchmarks/{name}.png)"
