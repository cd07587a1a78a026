"""ST-LPIPS (shift-tolerant LPIPS, Ghildyal & Liu, ECCV 2022), AlexNet variant, in plain
torch: a perceptual distance that, unlike LPIPS, is usable offline here — the
``stlpips-pytorch`` wheel ships the complete network (backbone and linear layers) in
``weights/vST0.0/alex_shift_tolerant.pth``. Only that file is read; the package itself is
not imported (it imports torchvision, IPython and torchsummary, none of which it needs for
this).

The network is AlexNet with its first convolution at stride 1 and every downsampling done
by a 3×3 binomial blur at stride 2 after reflection padding of 2 (the package's
``variant="shift_tolerant"``): taps after each of the five ReLUs; each tap unit-normalised
over channels, squared difference, a learned 1×1 weighting, averaged over the image and
summed over the taps. Inputs in [0, 1] are mapped to [−1, 1] and through LPIPS v0.1's
scaling layer.

Masked score: each tap's distance map upsampled bilinearly to the image (as LPIPS'
``spatial=True``), summed, and averaged with the mask as weights; without a mask, the
package's own value (each tap's map averaged at its resolution).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
import torch.nn.functional as F

from urhead.errors import InvalidArgumentError
from urhead.losses import masked_mean

WEIGHTS = Path("weights") / "vST0.0" / "alex_shift_tolerant.pth"
"""The weight file, inside the installed ``stlpips_pytorch`` package."""

_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
# The convolutions as (state-dict prefix, padding) and the blur filters' prefixes.
_CONVS = {
    "conv1": ("net.slice1.0", 2),
    "conv2": ("net.slice2.5", 2),
    "conv3": ("net.slice3.9", 1),
    "conv4": ("net.slice4.11", 1),
    "conv5": ("net.slice5.13", 1),
}
_BLURS = {"blur1": "net.slice1.1", "blur2": "net.slice2.4", "blur3": "net.slice3.8"}
_TAP_CHANNELS = (64, 192, 384, 256, 256)


def packaged_weights() -> Path | None:
    """The weight file of the installed ``stlpips-pytorch``, or None."""
    spec = importlib.util.find_spec("stlpips_pytorch")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / WEIGHTS
    return path if path.is_file() else None


class StLpips:
    """ST-LPIPS-alex with its weights loaded; call it on (H, W, 3) images in [0, 1]."""

    name = "stlpips_alex"

    def __init__(self, weights: Path):
        state = torch.load(weights, map_location="cpu", weights_only=True)
        self.convs = {
            key: (_get(state, f"{prefix}.weight", weights), _get(state, f"{prefix}.bias", weights))
            for key, (prefix, _) in _CONVS.items()
        }
        self.blurs = {key: _get(state, f"{prefix}.filt", weights) for key, prefix in _BLURS.items()}
        self.linears = []
        for i, channels in enumerate(_TAP_CHANNELS):
            w = _get(state, f"lin{i}.model.1.weight", weights).float()
            if tuple(w.shape) != (1, channels, 1, 1):
                raise InvalidArgumentError(
                    f"{weights}: lin{i}.model.1.weight must be (1, {channels}, 1, 1), "
                    f"got {tuple(w.shape)}"
                )
            self.linears.append(w)

    def _conv(self, key: str, x: torch.Tensor) -> torch.Tensor:
        w, b = self.convs[key]
        return F.conv2d(x, w, b, padding=_CONVS[key][1])

    def _blur(self, key: str, x: torch.Tensor) -> torch.Tensor:
        padded = F.pad(x, (2, 2, 2, 2), mode="reflect")
        return F.conv2d(padded, self.blurs[key], stride=2, groups=x.shape[1])

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        tap1 = F.relu(self._blur("blur1", self._conv("conv1", x)))
        x = self._blur("blur2", F.max_pool2d(tap1, 3, stride=1))
        tap2 = F.relu(self._conv("conv2", x))
        x = self._blur("blur3", F.max_pool2d(tap2, 3, stride=1))
        tap3 = F.relu(self._conv("conv3", x))
        tap4 = F.relu(self._conv("conv4", tap3))
        tap5 = F.relu(self._conv("conv5", tap4))
        return [tap1, tap2, tap3, tap4, tap5]

    @torch.no_grad()
    def features(self, image: torch.Tensor) -> list[torch.Tensor]:
        """The unit-normalised taps of an (H, W, 3) image in [0, 1] (computed once per
        image when it is compared with several others)."""
        x = image.permute(2, 0, 1)[None].float() * 2 - 1
        return [
            f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            for f in self._taps((x - _SHIFT) / _SCALE)
        ]

    @torch.no_grad()
    def distance(self, a: list[torch.Tensor], b: list[torch.Tensor], mask=None) -> float:
        """ST-LPIPS between two images' :meth:`features`, inside ``mask`` (H, W) if given."""
        maps = [
            F.conv2d((fa - fb) ** 2, lin) for fa, fb, lin in zip(a, b, self.linears, strict=True)
        ]
        if mask is None:
            return float(sum(m.mean() for m in maps))
        size = tuple(mask.shape)
        total = sum(
            F.interpolate(m, size=size, mode="bilinear", align_corners=False)[0, 0] for m in maps
        )
        return float(masked_mean(total, mask))

    def __call__(self, image, target, mask=None) -> float:
        return self.distance(self.features(image), self.features(target), mask)


def _get(state: dict, key: str, path: Path) -> torch.Tensor:
    if key not in state:
        raise InvalidArgumentError(f"{path}: no {key!r} (is this the ST-LPIPS alex file?)")
    return state[key].float()


def load_stlpips() -> tuple[StLpips | None, str | None]:
    """The metric from the installed package's weights, or None and a one-line note."""
    weights = packaged_weights()
    if weights is None:
        return None, "ST-LPIPS skipped: the stlpips-pytorch package (its weights) is missing"
    return StLpips(weights), None
