"""``urhead eval --error-breakdown``: every mask pixel lands in one part and one region, the
shares add up, the pooled PSNR is the in-mask PSNR, and error put in one place is reported
there."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from urhead.cli import main
from urhead.data import load_subject
from urhead.eval.breakdown import (
    BAND_PX,
    PARTS,
    ErrorBreakdown,
    pixel_parts,
    pixel_regions,
)
from urhead.head.model import REGION_NAMES
from urhead.losses import psnr
from urhead.model import load_avatar
from use_avatar import make_use_avatar


@pytest.fixture(scope="module")
def use(tmp_path_factory):
    return make_use_avatar(tmp_path_factory.mktemp("breakdown"))


def brute_force_band(mask: np.ndarray) -> np.ndarray:
    """A pixel is in the band when its (2·BAND_PX + 1)² window, clipped to the image, holds
    both mask and background pixels."""
    h, w = mask.shape
    band = np.zeros_like(mask, dtype=bool)
    for y in range(h):
        for x in range(w):
            window = mask[
                max(0, y - BAND_PX) : y + BAND_PX + 1, max(0, x - BAND_PX) : x + BAND_PX + 1
            ]
            band[y, x] = window.any() and not window.all()
    return band


def test_parts_against_brute_force():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:40, :48]
    solid = ((yy - 18) ** 2 / 150 + (xx - 25) ** 2 / 260) < 1  # an ellipse
    mask = torch.from_numpy(np.where(solid, 1.0, 0.0).astype(np.float32))
    mask[solid & (rng.random(solid.shape) < 0.1)] = 0.7  # soft values count as inside
    tri_id = torch.from_numpy(np.where(solid & (xx < 30), 5, -1).astype(np.int32))
    parts = pixel_parts(mask, tri_id).numpy()
    band = brute_force_band(solid)
    assert (parts == 0).sum() > 0 and np.array_equal(parts == 0, band)
    assert np.array_equal(parts == 1, ~band & (tri_id.numpy() < 0))
    assert np.array_equal(parts == 2, ~band & (tri_id.numpy() >= 0))


def test_regions_take_the_nearest_covered_pixel():
    tri_id = torch.full((6, 10), -1, dtype=torch.int32)
    tri_id[:, :3] = 0  # face 0 on the left
    tri_id[:, 8:] = 1  # face 1 on the right
    face_region = torch.tensor([REGION_NAMES.index("ears"), REGION_NAMES.index("scalp")])
    regions = pixel_regions(tri_id, face_region)
    ears, scalp = REGION_NAMES.index("ears"), REGION_NAMES.index("scalp")
    assert (regions[:, :5] == ears).all()  # columns 3, 4 are nearer the left
    assert (regions[:, 6:] == scalp).all()  # columns 6, 7 nearer the right
    assert (pixel_regions(torch.full((4, 4), -1), face_region) == -1).all()


def test_error_put_in_one_cell_is_reported_there_and_psnr_is_the_in_mask_psnr():
    h, w = 24, 32
    g = torch.Generator().manual_seed(0)
    target = torch.rand(h, w, 3, generator=g)
    mask = torch.zeros(h, w)
    mask[4:20, 6:26] = 1.0
    mask[4, 6:26] = 0.5  # a soft edge row weighs half
    parts = torch.full((h, w), 2, dtype=torch.int64)
    parts[4:7, :] = 0
    regions = torch.full((h, w), REGION_NAMES.index("face"), dtype=torch.int64)
    regions[:, 20:] = REGION_NAMES.index("ears")
    image = target.clone()
    image[10:14, 22:25] += 0.2  # on the mesh, ears only
    acc = ErrorBreakdown()
    acc.add(image, target, mask, parts, regions)
    report = acc.report()
    in_mask = psnr(image.double(), target.double(), mask.double())
    assert report["psnr_pooled"] == pytest.approx(float(in_mask), abs=1e-9)
    assert report["regions"]["ears"]["error_share"] == pytest.approx(1.0)
    assert report["parts"]["on the mesh"]["error_share"] == pytest.approx(1.0)
    assert report["parts"]["silhouette band"]["error_share"] == 0.0
    assert report["parts"]["silhouette band"]["psnr"] is None
    ears_area = float(mask[:, 20:].sum() / mask.sum())
    assert report["regions"]["ears"]["area_share"] == pytest.approx(ears_area)
    assert sum(c["area_share"] for c in report["cells"]) == pytest.approx(1.0)
    cell = [c for c in report["cells"] if c["region"] == "ears" and c["part"] == "on the mesh"]
    mse = float(((image - target).double() ** 2)[10:14, 22:25].sum()) / (
        3 * float(mask[7:20, 20:].sum())
    )
    assert cell[0]["psnr"] == pytest.approx(-10 * np.log10(mse), abs=1e-9)
    with pytest.raises(ValueError, match="no mask pixels"):
        ErrorBreakdown().report()


@pytest.mark.parametrize("refine", [False, True])
def test_eval_error_breakdown(use, tmp_path, capsys, refine):
    out = tmp_path / "eval.json"
    argv = ["eval", str(use.avatar_dir), "--json", str(out), "--error-breakdown", "--no-stlpips"]
    argv += ["--refine-flame", "--refine-steps", "2", "--refine-full-steps", "0"] if refine else []
    assert main(argv) == 0
    assert "where the error sits" in capsys.readouterr().out
    result = json.loads(out.read_text())
    report = result["error_breakdown"]
    assert report["flame_parameters"] == ("refined" if refine else "tracked")
    assert report["frames"] == result["frames"]
    for key in ("parts", "regions"):
        assert sum(e["error_share"] for e in report[key].values()) == pytest.approx(1.0)
        assert sum(e["area_share"] for e in report[key].values()) == pytest.approx(1.0)
    assert set(report["parts"]) <= set(PARTS) and "silhouette band" in report["parts"]
    if refine:
        return
    # The pooled PSNR from the renders directly: Σ m·e² / (3 Σ m) over all held-out frames.
    avatar = load_avatar(use.avatar_dir)
    error = weight = 0.0
    with torch.no_grad():
        for f in load_subject(use.subject_dir).test:
            image = avatar.render(avatar.params_from_flame(f.flame), f.camera).image.clamp(0, 1)
            error += float((((image - f.image) ** 2).sum(-1) * f.mask).sum())
            weight += float(f.mask.sum())
    assert report["psnr_pooled"] == pytest.approx(-10 * np.log10(error / (3 * weight)), abs=1e-4)


def test_eval_without_breakdown_reports_none(use, tmp_path):
    out = tmp_path / "eval.json"
    assert main(["eval", str(use.avatar_dir), "--json", str(out), "--no-stlpips"]) == 0
    assert json.loads(out.read_text())["error_breakdown"] is None
