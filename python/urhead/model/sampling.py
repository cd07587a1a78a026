"""Where Gaussians live: UV points on the atlas, drawn uniformly or in proportion to the
accumulated UV-space error (the paper's error-driven sampling, Sec. 3.3)."""

from __future__ import annotations

import numpy as np
import torch

from urhead.head.uv import UvLookup


class UvSurface:
    """Draws UV points that lie on the atlas and locates their faces."""

    def __init__(self, uv_coords: np.ndarray, uv_faces: np.ndarray):
        self.lookup = UvLookup(uv_coords, uv_faces)

    def locate(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``uv`` (N, 2) → ``(face (N,) int64, bary (N, 3))``, face −1 off the atlas."""
        return self.lookup.locate(uv)

    def uniform(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 2) float32 points uniform over the atlas' UV area (rejection sampling)."""
        if n <= 0:
            return np.zeros((0, 2), np.float32)
        out = []
        have = 0
        while have < n:
            uv = rng.random((max(2 * (n - have), 64), 2))
            face, _ = self.locate(uv)
            hits = uv[face >= 0]
            out.append(hits)
            have += len(hits)
        return np.concatenate(out)[:n].astype(np.float32)


class ErrorAccumulator:
    """The visibility-normalised UV error w(u, v) = (1/N) Σ_t V·E_uv, on a G × G grid.

    Each rendered frame adds its per-pixel photometric error at the UV coordinate the pixel
    sees (the pixel is then a visible observation of that cell). Cells are coarser than the
    maps on purpose: a 512² image sees each 2048² texel rarely, and sampling needs a
    density, not a per-texel value.
    """

    def __init__(self, grid: int):
        self.grid = int(grid)
        self.error = torch.zeros(self.grid * self.grid, dtype=torch.float64)
        self.count = torch.zeros(self.grid * self.grid, dtype=torch.float64)

    def add(self, uv: torch.Tensor, error: torch.Tensor) -> None:
        """uv: (P, 2) UVs seen at covered pixels; error: (P,) their photometric error."""
        g = self.grid
        col = (uv[:, 0] * g).long().clamp(0, g - 1)
        row = ((1 - uv[:, 1]) * g).long().clamp(0, g - 1)
        cell = row * g + col
        self.error += torch.bincount(cell, error.double(), minlength=g * g)
        self.count += torch.bincount(cell, minlength=g * g).double()

    def density(self) -> torch.Tensor:
        """(G·G,) normalised error per cell, 0 where never seen."""
        return torch.where(self.count > 0, self.error / self.count.clamp_min(1), 0.0)

    def sample(self, n: int, surface: UvSurface, rng: np.random.Generator) -> np.ndarray:
        """(≤ n, 2) float32 UV points drawn in proportion to the density, jittered
        uniformly inside their cell and kept when they land on the atlas."""
        w = self.density().numpy()
        total = w.sum()
        if n <= 0 or not total > 0:
            return np.zeros((0, 2), np.float32)
        cells = rng.choice(w.size, size=n, p=w / total)
        g = self.grid
        row, col = np.divmod(cells, g)
        jitter = rng.random((n, 2))
        uv = np.stack([(col + jitter[:, 0]) / g, 1 - (row + jitter[:, 1]) / g], 1)
        face, _ = surface.locate(uv)
        return uv[face >= 0].astype(np.float32)

    def reset(self) -> None:
        self.error.zero_()
        self.count.zero_()

    def state(self) -> dict:
        return {"error": self.error.clone(), "count": self.count.clone()}

    def load_state(self, state: dict) -> None:
        self.error.copy_(state["error"])
        self.count.copy_(state["count"])
