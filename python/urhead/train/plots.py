"""Plots of a fit: held-out PSNR against training time."""

from __future__ import annotations

import io
from pathlib import Path

from urhead._atomic import write_bytes_atomically


def plot_psnr_vs_time(history: list, path: Path, title: str) -> None:
    """Writes a PNG of ``history`` rows ``(seconds, iteration, psnr)``, atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4))
    if history:
        seconds, iterations, values = zip(*history, strict=True)
        ax.plot(seconds, values, marker="o", markersize=3)
        ax.annotate(
            f"{values[-1]:.2f} dB @ {seconds[-1]:.0f} s, it {iterations[-1]}",
            (seconds[-1], values[-1]),
            textcoords="offset points",
            xytext=(-10, -14),
            ha="right",
            fontsize=8,
        )
    ax.set_xlabel("training wall-clock seconds")
    ax.set_ylabel("held-out PSNR (dB, inside the mask)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    image = io.BytesIO()
    fig.savefig(image, dpi=120, format="png")
    plt.close(fig)
    write_bytes_atomically(path, image.getvalue())
