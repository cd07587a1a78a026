"""Shared fixtures: small synthetic skinned models with FLAME's joint structure."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch


@dataclass
class SkinnedModel:
    v_template: torch.Tensor  # (V, 3)
    shapedirs: torch.Tensor  # (V, 3, NB)
    posedirs: torch.Tensor  # (9·(J−1), V·3)
    j_regressor: torch.Tensor  # (J, V)
    parents: torch.Tensor  # (J,)
    lbs_weights: torch.Tensor  # (V, J)

    def tables(self):
        return (
            self.v_template,
            self.shapedirs,
            self.posedirs,
            self.j_regressor,
            self.parents,
            self.lbs_weights,
        )


def make_skinned_model(
    num_verts=200, num_betas=20, num_joints=5, dtype=torch.float64, seed=0, dyadic_weights=False
) -> SkinnedModel:
    """A random model with FLAME's chain (parents [-1, 0, 1, 1, 1]). With
    ``dyadic_weights`` the skinning weights are multiples of 1/4, so they sum to exactly 1."""
    g = torch.Generator().manual_seed(seed)
    v, nb, j = num_verts, num_betas, num_joints

    def rand(*shape, scale=1.0):
        return ((torch.rand(*shape, generator=g, dtype=torch.float64) * 2 - 1) * scale).to(dtype)

    j_regressor = torch.rand(j, v, generator=g, dtype=torch.float64)
    j_regressor = (j_regressor / j_regressor.sum(1, keepdim=True)).to(dtype)
    if dyadic_weights:
        picks = torch.randint(0, j, (v, 4), generator=g)
        weights = torch.zeros(v, j, dtype=torch.float64)
        weights.scatter_add_(1, picks, torch.full((v, 4), 0.25, dtype=torch.float64))
    else:
        weights = torch.rand(v, j, generator=g, dtype=torch.float64) ** 4
        weights = weights / weights.sum(1, keepdim=True)
    parents = torch.tensor([-1, 0] + [1] * (j - 2), dtype=torch.int64)[:j]
    return SkinnedModel(
        v_template=rand(v, 3, scale=0.1),
        shapedirs=rand(v, 3, nb, scale=1e-2),
        posedirs=rand(9 * (j - 1), v * 3, scale=1e-2),
        j_regressor=j_regressor,
        parents=parents,
        lbs_weights=weights.to(dtype),
    )


@pytest.fixture
def model64() -> SkinnedModel:
    return make_skinned_model(dtype=torch.float64)


@pytest.fixture
def model32() -> SkinnedModel:
    return make_skinned_model(dtype=torch.float32)
