"""Shared helpers for sections: number formatting, markdown tables, figure saving."""

from __future__ import annotations

from pathlib import Path


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
