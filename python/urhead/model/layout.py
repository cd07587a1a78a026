"""Channel layout of the packed UV-map table Θ_u = {C, N, D, O, S}.

All maps live in one (R, R, channels) float32 table so one bilinear lookup serves every
consumer and one sparse-Adam step (with per-channel learning rates) updates them. The
Gaussian-only maps (O, S) are left out when a fit has no Gaussian branch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch


class MapSamples(NamedTuple):
    """Map values at some UV points (leading dimensions ``...``)."""

    color: torch.Tensor
    """(..., 3K) SH coefficients, coefficient-major."""
    normal: torch.Tensor
    """(..., 3) rest-pose normal."""
    displacement: torch.Tensor
    """(...,) metres."""
    opacity: torch.Tensor | None
    """(...,) logit; None without the Gaussian branch."""
    scale: torch.Tensor | None
    """(..., 3) log standard deviations; None without the Gaussian branch."""


@dataclass(frozen=True)
class MapLayout:
    """Where each map sits in the channel dimension.

    - C: SH colour, (degree + 1)² coefficients × RGB, stored coefficient-major
      (channel 3k + c is coefficient k of colour c), so ``C.view(..., K, 3)``.
    - N: rest-pose normal (3, not necessarily unit; normalised where used).
    - D: displacement along the posed normal, metres (1).
    - O: opacity logit (1), Gaussian branch only.
    - S: log standard deviations (3; the third is along the normal), Gaussian branch only.
    """

    sh_degree: int = 3
    gaussians: bool = True

    def __post_init__(self):
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in [0, 3], got {self.sh_degree}")

    @property
    def sh_coeffs(self) -> int:
        return (self.sh_degree + 1) ** 2

    @property
    def color(self) -> slice:
        return slice(0, 3 * self.sh_coeffs)

    @property
    def normal(self) -> slice:
        start = 3 * self.sh_coeffs
        return slice(start, start + 3)

    @property
    def displacement(self) -> int:
        return 3 * self.sh_coeffs + 3

    @property
    def opacity(self) -> int:
        self._require_gaussians("opacity")
        return 3 * self.sh_coeffs + 4

    @property
    def scale(self) -> slice:
        self._require_gaussians("scale")
        start = 3 * self.sh_coeffs + 5
        return slice(start, start + 3)

    @property
    def channels(self) -> int:
        return 3 * self.sh_coeffs + (8 if self.gaussians else 4)

    def split(self, samples: torch.Tensor) -> MapSamples:
        """(..., channels) map samples → their maps, by one ``split`` (its backward is
        one concatenation, where per-map slicing would allocate a zero buffer per map)."""
        sizes = [3 * self.sh_coeffs, 3, 1] + ([1, 3] if self.gaussians else [])
        parts = samples.split(sizes, dim=-1)
        if not self.gaussians:
            return MapSamples(parts[0], parts[1], parts[2][..., 0], None, None)
        return MapSamples(parts[0], parts[1], parts[2][..., 0], parts[3][..., 0], parts[4])

    def channel_rates(self, color, normal, displacement, opacity, scale) -> torch.Tensor:
        """(channels,) float32 learning rates, one per channel."""
        lr = torch.empty(self.channels, dtype=torch.float32)
        lr[self.color] = color
        lr[self.normal] = normal
        lr[self.displacement] = displacement
        if self.gaussians:
            lr[self.opacity] = opacity
            lr[self.scale] = scale
        return lr

    def _require_gaussians(self, name: str) -> None:
        if not self.gaussians:
            raise AttributeError(f"a mesh-only layout has no {name} map")
