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
    offset: torch.Tensor | None = None
    """(...,) the Gaussians' own offset along the normal, metres; None unless the layout
    has it."""
    shading: torch.Tensor | None = None
    """(..., 9) pose-driven shading coefficients; None unless the layout has them."""


SHADING_FEATURES = 9
"""Pose-driven shading: one coefficient per entry of the surface's rotation R − I."""


def shading_features(rotation: torch.Tensor) -> torch.Tensor:
    """(P, 9) the shading maps' features, the entries of R − I, from (P, 3, 3) rotations."""
    return (rotation - torch.eye(3, dtype=rotation.dtype)).reshape(-1, SHADING_FEATURES)


def shading_gain(shading: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """(P,) the colour's factor 1 + Σ A_ij (R − I)_ij, from the shading maps' samples
    ``shading (P, 9)`` and :func:`shading_features` of the rotations."""
    return 1 + (shading * features).sum(-1)


@dataclass(frozen=True)
class MapLayout:
    """Where each map sits in the channel dimension, in this order:

    - C: SH colour, (degree + 1)² coefficients × RGB, stored coefficient-major
      (channel 3k + c is coefficient k of colour c), so ``C.view(..., K, 3)``.
    - N: rest-pose normal (3, not necessarily unit; normalised where used).
    - D: displacement along the posed normal, metres (1).
    - O: opacity logit (1), Gaussian branch only.
    - S: log standard deviations (3; the third is along the normal), Gaussian branch only.
    - E: the Gaussians' own offset along the normal (1), on top of D, metres; only with
      ``offsets`` (it lets Gaussians leave the surface where hair is, while the mesh stays).
    - A: pose-driven shading (9), only with ``shading``: colour × (1 + Σ A_ij (R − I)_ij)
      with R the surface's skinning rotation — light fixed in the room seen from a
      turning head, to first order in the rotation.
    """

    sh_degree: int = 3
    gaussians: bool = True
    offsets: bool = False
    shading: bool = False

    def __post_init__(self):
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in [0, 3], got {self.sh_degree}")
        if self.offsets and not self.gaussians:
            raise ValueError("the offset map E belongs to the Gaussian branch")

    @property
    def sh_coeffs(self) -> int:
        return (self.sh_degree + 1) ** 2

    def _sizes(self) -> list[int]:
        """Channel counts of the maps present, in storage order."""
        sizes = [3 * self.sh_coeffs, 3, 1]
        sizes += [1, 3] if self.gaussians else []
        sizes += [1] if self.offsets else []
        sizes += [SHADING_FEATURES] if self.shading else []
        return sizes

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
    def offset(self) -> int:
        if not self.offsets:
            raise AttributeError("this layout has no offset map E")
        return 3 * self.sh_coeffs + 8

    @property
    def shading_maps(self) -> slice:
        if not self.shading:
            raise AttributeError("this layout has no shading maps A")
        end = self.channels
        return slice(end - SHADING_FEATURES, end)

    @property
    def channels(self) -> int:
        return sum(self._sizes())

    def named_maps(self) -> list[tuple[str, slice]]:
        """``(name, channels)`` of every map present, in storage order (for reports)."""
        names = ["colour C", "normal N", "displacement D"]
        names += ["opacity O", "scale S"] if self.gaussians else []
        names += ["offset E"] if self.offsets else []
        names += ["shading A"] if self.shading else []
        out, start = [], 0
        for name, size in zip(names, self._sizes(), strict=True):
            out.append((name, slice(start, start + size)))
            start += size
        return out

    def split(self, samples: torch.Tensor) -> MapSamples:
        """(..., channels) map samples → their maps, by one ``split`` (its backward is
        one concatenation, where per-map slicing would allocate a zero buffer per map)."""
        parts = list(samples.split(self._sizes(), dim=-1))
        shading = parts.pop() if self.shading else None
        offset = parts.pop()[..., 0] if self.offsets else None
        color, normal, displacement = parts[0], parts[1], parts[2][..., 0]
        if not self.gaussians:
            return MapSamples(color, normal, displacement, None, None, None, shading)
        opacity, scale = parts[3][..., 0], parts[4]
        return MapSamples(color, normal, displacement, opacity, scale, offset, shading)

    def channel_rates(
        self, color, normal, displacement, opacity, scale, offset=0.0, sh_rest=1.0, shading=0.0
    ) -> torch.Tensor:
        """(channels,) float32 learning rates, one per channel; ``sh_rest`` scales the
        colour rate of the SH bands above DC."""
        lr = torch.empty(self.channels, dtype=torch.float32)
        lr[self.color] = color * sh_rest
        lr[0:3] = color
        lr[self.normal] = normal
        lr[self.displacement] = displacement
        if self.gaussians:
            lr[self.opacity] = opacity
            lr[self.scale] = scale
        if self.offsets:
            lr[self.offset] = offset
        if self.shading:
            lr[self.shading_maps] = shading
        return lr

    def _require_gaussians(self, name: str) -> None:
        if not self.gaussians:
            raise AttributeError(f"a mesh-only layout has no {name} map")
