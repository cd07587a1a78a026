"""Where an avatar's error sits: the squared error inside the head masks, pooled over
frames, split by where each pixel lies (``urhead eval --error-breakdown``).

Every mask pixel falls in exactly one *part*:
- ``silhouette band``: within :data:`BAND_PX` pixels of the mask's edge (the matte's
  antialiased edge and the pixels either side of it, where alignment shows);
- ``beyond the mesh``: inside the mask where the mesh covers nothing (hair volume, ears or
  a silhouette the surface does not reach; what only Gaussians can draw);
- ``on the mesh``: the rest.
and in exactly one *region* of the head (:data:`~urhead.head.model.REGION_NAMES`): the
region of the triangle the pixel sees, or for a pixel the mesh misses the region of the
nearest pixel it covers. So "the ears' silhouette band" and "the hair behind the ears"
(beyond the mesh, nearest the ears) are told apart from the ears' interior.

Each cell reports its share of the error, its share of the mask, and its PSNR. A pixel
counts with its mask value as weight, as in the in-mask PSNR (FORMATS.md "Evaluation
protocol").
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from urhead.head.model import REGION_NAMES
from urhead.ops import nearest_covered_pixel

BAND_PX = 2
"""Half-width of the silhouette band, pixels."""

PARTS = ("silhouette band", "beyond the mesh", "on the mesh")


def pixel_parts(mask: torch.Tensor, tri_id: torch.Tensor) -> torch.Tensor:
    """(H, W) int64 index into :data:`PARTS` of each pixel, from the frame's (H, W) mask
    and the (H, W) triangle id the mesh rasterizes there (−1 where it misses)."""
    solid = (mask > 0.5).to(torch.float32)[None, None]
    size = 2 * BAND_PX + 1
    grown = F.max_pool2d(solid, size, 1, BAND_PX)[0, 0] > 0.5
    shrunk = -F.max_pool2d(-solid, size, 1, BAND_PX)[0, 0] > 0.5
    band = grown & ~shrunk
    parts = torch.full(mask.shape, 2, dtype=torch.int64)
    parts[tri_id < 0] = 1
    parts[band] = 0
    return parts


def pixel_regions(tri_id: torch.Tensor, face_region: torch.Tensor) -> torch.Tensor:
    """(H, W) int64 region of each pixel: its triangle's, or the nearest covered pixel's
    where the mesh misses; −1 everywhere when the mesh covers nothing."""
    covered = tri_id >= 0
    if not bool(covered.any()):
        return torch.full(tri_id.shape, -1, dtype=torch.int64)
    nearest = nearest_covered_pixel(covered)
    return face_region[tri_id.reshape(-1)[nearest].long()].reshape(tri_id.shape)


class ErrorBreakdown:
    """Accumulates mask-weighted squared error and mask weight per (part, region) cell."""

    def __init__(self):
        cells = len(PARTS) * len(REGION_NAMES)
        self.error = torch.zeros(cells, dtype=torch.float64)
        self.weight = torch.zeros(cells, dtype=torch.float64)
        self.frames = 0

    def add(self, image, target, mask, parts, regions) -> None:
        """image, target (H, W, 3); mask (H, W) in [0, 1]; parts, regions (H, W) int64 from
        :func:`pixel_parts`, :func:`pixel_regions`."""
        inside = (mask > 0) & (regions >= 0)
        cell = (parts * len(REGION_NAMES) + regions)[inside]
        weight = mask[inside].double()
        error = ((image - target).double() ** 2).sum(-1)[inside] * weight
        size = self.error.numel()
        self.error += torch.bincount(cell, error, minlength=size)
        self.weight += torch.bincount(cell, weight, minlength=size)
        self.frames += 1

    def report(self) -> dict:
        """JSON-ready: the pooled in-mask PSNR, and per part, per region and per (part,
        region) cell with any mask weight: ``error_share``, ``area_share`` (fractions)
        and ``psnr`` (dB, None where the error is zero)."""
        total_error, total_weight = float(self.error.sum()), float(self.weight.sum())
        if total_weight == 0:
            raise ValueError("no mask pixels: nothing to break down")

        def entry(error: float, weight: float) -> dict:
            mse = error / (3 * weight)
            return {
                "error_share": error / total_error if total_error > 0 else 0.0,
                "area_share": weight / total_weight,
                "psnr": -10 * math.log10(mse) if mse > 0 else None,
            }

        grid_error = self.error.reshape(len(PARTS), len(REGION_NAMES))
        grid_weight = self.weight.reshape(len(PARTS), len(REGION_NAMES))
        cells = [
            {"part": part, "region": region, **entry(float(e), float(w))}
            for part, errors, weights in zip(PARTS, grid_error, grid_weight, strict=True)
            for region, e, w in zip(REGION_NAMES, errors, weights, strict=True)
            if w > 0
        ]
        return {
            "frames": self.frames,
            "band_px": BAND_PX,
            "psnr_pooled": entry(total_error, total_weight)["psnr"],
            "parts": {
                part: entry(float(grid_error[i].sum()), float(grid_weight[i].sum()))
                for i, part in enumerate(PARTS)
                if grid_weight[i].sum() > 0
            },
            "regions": {
                region: entry(float(grid_error[:, j].sum()), float(grid_weight[:, j].sum()))
                for j, region in enumerate(REGION_NAMES)
                if grid_weight[:, j].sum() > 0
            },
            "cells": cells,
        }


@torch.no_grad()
def error_breakdown(
    avatar, frames: Sequence, params: Sequence, *, occlusion_aware: bool = True
) -> dict:
    """Renders each of ``frames`` with its entry of ``params`` and breaks its in-mask error
    down (module docstring); :meth:`ErrorBreakdown.report` of them all."""
    face_region = torch.from_numpy(np.asarray(avatar.head.face_region(), np.int64))
    breakdown = ErrorBreakdown()
    for frame, p in zip(frames, params, strict=True):
        out = avatar.render(p, frame.camera, occlusion_aware=occlusion_aware)
        tri_id = out.mesh.tri_id
        breakdown.add(
            out.image.clamp(0, 1),
            frame.image,
            frame.mask,
            pixel_parts(frame.mask, tri_id),
            pixel_regions(tri_id, face_region),
        )
    return breakdown.report()


def format_breakdown(report: dict, rows: int = 8) -> str:
    """A short table: each part, then the ``rows`` cells holding the most error."""
    lines = [
        f"where the error sits ({report['frames']} frames, pooled in-mask PSNR "
        f"{report['psnr_pooled']:.2f} dB; band: ±{report['band_px']} px of the mask's edge)"
    ]

    def line(name: str, e: dict) -> str:
        db = "—" if e["psnr"] is None else f"{e['psnr']:.2f} dB"
        return (
            f"  {name:<34} {100 * e['error_share']:5.1f} % of the error in "
            f"{100 * e['area_share']:5.1f} % of the mask ({db})"
        )

    lines += [line(part, e) for part, e in report["parts"].items()]
    top = sorted(report["cells"], key=lambda c: -c["error_share"])[:rows]
    lines += [line(f"{c['region']}, {c['part']}", c) for c in top]
    return "\n".join(lines)
