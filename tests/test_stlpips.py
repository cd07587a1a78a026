"""ST-LPIPS from the stlpips-pytorch wheel's own weights: the same numbers as the
package's implementation, zero for equal images, masked scores, and its place in eval."""

from __future__ import annotations

import json
import sys
import types

import pytest
import torch

from urhead.cli import main
from urhead.eval.stlpips import StLpips, load_stlpips, packaged_weights
from use_avatar import make_use_avatar


@pytest.fixture(scope="module")
def metric() -> StLpips:
    net, note = load_stlpips()
    assert net is not None, note
    return net


def package_reference(monkeypatch):
    """The package's own LPIPS(alex, shift_tolerant). Its modules import torchvision,
    IPython and torchsummary without using them for this network: stand-ins let it load."""
    for name in ("torchvision", "IPython", "torchsummary"):
        stub = types.ModuleType(name)
        stub.models = stub.embed = stub.summary = None
        monkeypatch.setitem(sys.modules, name, stub)
    from stlpips_pytorch import stlpips

    return stlpips.LPIPS(net="alex", variant="shift_tolerant", verbose=False)


def test_matches_the_package_implementation(metric, monkeypatch):
    reference = package_reference(monkeypatch)
    g = torch.Generator().manual_seed(0)
    for h, w in ((64, 64), (96, 80)):
        a = torch.rand(h, w, 3, generator=g)
        b = (a + 0.1 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
        with torch.no_grad():
            expected = reference(
                a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], normalize=True
            ).item()
        assert metric(a, b) == pytest.approx(expected, rel=1e-5, abs=1e-9)


def test_equal_images_score_zero_and_the_mask_selects(metric):
    g = torch.Generator().manual_seed(1)
    a = torch.rand(64, 64, 3, generator=g)
    b = a.clone()
    b[:, 32:] = torch.rand(64, 32, 3, generator=g)  # differ on the right half only
    assert metric(a, a) == 0.0
    left, right = torch.zeros(64, 64), torch.zeros(64, 64)
    left[:, :24], right[:, 40:] = 1, 1
    assert metric(a, b, right) > 5 * metric(a, b, left)


def test_weights_come_from_the_installed_wheel():
    path = packaged_weights()
    assert path is not None and path.name == "alex_shift_tolerant.pth"
    assert "stlpips_pytorch" in path.parts


def test_eval_reports_stlpips_and_its_temporal_change(tmp_path, capsys, metric):
    use = make_use_avatar(tmp_path / "use")
    assert main(["eval", str(use.avatar_dir), "--json", "-"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    assert "ST-LPIPS alex" in captured.err
    per_frame = result["per_frame"]["stlpips_alex"]
    assert len(per_frame) == result["frames"] and min(per_frame) > 0
    assert result["stlpips_alex"] == pytest.approx(sum(per_frame) / len(per_frame))
    assert result["temporal_stlpips_alex_mean"] >= 0
    assert main(["eval", str(use.avatar_dir), "--json", "-", "--no-stlpips"]) == 0
    skipped = json.loads(capsys.readouterr().out)
    assert skipped["stlpips_alex"] is None and skipped["temporal_stlpips_alex_mean"] is None
    assert skipped["psnr"] == result["psnr"]
