"""LPIPS (Zhang et al. 2018, version 0.1) in plain torch, from weight files on disk — it
never downloads anything (nothing can be downloaded here), and needs neither the
``lpips`` package nor torchvision.

Two files per variant, found in a weights directory:

| variant | backbone (torchvision ImageNet weights) | linear layers (lpips v0.1) |
|---|---|---|
| ``alex`` | ``alexnet-owt-7be5be79.pth`` (any ``alexnet*.pth``) | ``alex.pth`` |
| ``vgg`` | ``vgg16-397923af.pth`` (any ``vgg16*.pth``) | ``vgg.pth`` |

The directory is ``--lpips-weights DIR``, else ``$URHEAD_LPIPS_DIR``, else
``~/.cache/urhead/lpips``; backbones are also looked up in torch's hub cache
(``$TORCH_HOME/hub/checkpoints``, default ``~/.cache/torch/hub/checkpoints``), where
torchvision keeps them. The linear files are ``lpips/weights/v0.1/*.pth`` of the lpips
package.

Masked score: the spatial LPIPS map (each layer's distance upsampled bilinearly to the
image, as lpips' ``spatial=True``) averaged with the mask as weights.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
import torch.nn.functional as F

from urhead.errors import InvalidArgumentError
from urhead.losses import masked_mean

# (conv layers as (in, out, kernel, stride, padding), indices of features.N, pools after,
#  taps: the number of convs after which a feature map is taken)
_ALEX = {
    "convs": [
        (3, 64, 11, 4, 2),
        (64, 192, 5, 1, 2),
        (192, 384, 3, 1, 1),
        (384, 256, 3, 1, 1),
        (256, 256, 3, 1, 1),
    ],
    "indices": [0, 3, 6, 8, 10],
    "pool_before": {1, 2},  # max-pool 3/2 before these convs
    "pool": (3, 2),
    "taps": [0, 1, 2, 3, 4],
    "backbone_glob": "alexnet*.pth",
    "linear": "alex.pth",
}
_VGG_CHANNELS = [
    (3, 64),
    (64, 64),
    (64, 128),
    (128, 128),
    (128, 256),
    (256, 256),
    (256, 256),
    (256, 512),
    (512, 512),
    (512, 512),
    (512, 512),
    (512, 512),
    (512, 512),
]
_VGG = {
    "convs": [(i, o, 3, 1, 1) for i, o in _VGG_CHANNELS],
    "indices": [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28],
    "pool_before": {2, 4, 7, 10},
    "pool": (2, 2),
    "taps": [1, 3, 6, 9, 12],
    "backbone_glob": "vgg16*.pth",
    "linear": "vgg.pth",
}
VARIANTS = {"alex": _ALEX, "vgg": _VGG}

_SHIFT = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
_SCALE = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)


def weight_directories(explicit: Path | None) -> list[Path]:
    """Where weights are looked for, in order."""
    if explicit is not None:
        return [Path(explicit)]
    dirs = []
    if os.environ.get("URHEAD_LPIPS_DIR"):
        dirs.append(Path(os.environ["URHEAD_LPIPS_DIR"]))
    dirs.append(Path.home() / ".cache" / "urhead" / "lpips")
    return dirs


def _hub_checkpoints() -> Path:
    torch_home = os.environ.get("TORCH_HOME", str(Path.home() / ".cache" / "torch"))
    return Path(torch_home) / "hub" / "checkpoints"


def find_weights(variant: str, explicit: Path | None = None) -> tuple[Path, Path] | None:
    """(backbone, linear) files of ``variant``, or None when either is missing."""
    spec = VARIANTS[variant]
    dirs = weight_directories(explicit)
    linear = next((d / spec["linear"] for d in dirs if (d / spec["linear"]).is_file()), None)
    backbone = None
    for d in [*dirs, _hub_checkpoints()]:
        hits = sorted(d.glob(spec["backbone_glob"])) if d.is_dir() else []
        if hits:
            backbone = hits[0]
            break
    return None if linear is None or backbone is None else (backbone, linear)


class Lpips:
    """One LPIPS variant with its weights loaded; call it on (H, W, 3) images in [0, 1]."""

    def __init__(self, variant: str, backbone: Path, linear: Path):
        spec = VARIANTS[variant]
        self.variant = variant
        self.spec = spec
        state = torch.load(backbone, map_location="cpu", weights_only=True)
        lin_state = torch.load(linear, map_location="cpu", weights_only=True)
        self.convs = []
        for idx, (cin, cout, k, _, _) in zip(spec["indices"], spec["convs"], strict=True):
            w, b = (
                _get(state, f"features.{idx}.weight", backbone),
                _get(state, f"features.{idx}.bias", backbone),
            )
            if tuple(w.shape) != (cout, cin, k, k) or tuple(b.shape) != (cout,):
                raise InvalidArgumentError(
                    f"{backbone}: features.{idx} must be ({cout}, {cin}, {k}, {k}), "
                    f"got {tuple(w.shape)}"
                )
            self.convs.append((w.float(), b.float()))
        self.linears = []
        for i, tap in enumerate(spec["taps"]):
            w = _get(lin_state, f"lin{i}.model.1.weight", linear).float()
            channels = spec["convs"][tap][1]
            if tuple(w.shape) != (1, channels, 1, 1):
                raise InvalidArgumentError(
                    f"{linear}: lin{i}.model.1.weight must be (1, {channels}, 1, 1), "
                    f"got {tuple(w.shape)}"
                )
            self.linears.append(w)

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        spec = self.spec
        feats = []
        for i, ((w, b), (_, _, _, stride, pad)) in enumerate(
            zip(self.convs, spec["convs"], strict=True)
        ):
            if i in spec["pool_before"]:
                x = F.max_pool2d(x, *spec["pool"])
            x = F.relu(F.conv2d(x, w, b, stride=stride, padding=pad))
            if i in spec["taps"]:
                feats.append(x)
        return feats

    @torch.no_grad()
    def distance_map(self, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """(H, W) spatial LPIPS between two (H, W, 3) images in [0, 1]."""
        h, w = image.shape[:2]
        pair = torch.stack([image, target]).permute(0, 3, 1, 2).float() * 2 - 1
        feats = self._features((pair - _SHIFT) / _SCALE)
        total = torch.zeros(1, 1, h, w)
        for f, lin in zip(feats, self.linears, strict=True):
            f = f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = F.conv2d((f[:1] - f[1:]) ** 2, lin)
            total = total + F.interpolate(d, size=(h, w), mode="bilinear", align_corners=False)
        return total[0, 0]

    def __call__(self, image, target, mask=None) -> float:
        return float(masked_mean(self.distance_map(image, target), mask))


def _get(state: dict, key: str, path: Path) -> torch.Tensor:
    if key not in state:
        raise InvalidArgumentError(f"{path}: no {key!r} (is this the right weight file?)")
    return state[key]


def load_lpips(explicit: Path | None = None) -> tuple[dict[str, Lpips], list[str]]:
    """The variants whose weights are found, and a one-line note per skipped variant."""
    if explicit is not None and not Path(explicit).is_dir():
        raise FileNotFoundError(f"--lpips-weights {explicit}: no such directory")
    found, notes = {}, []
    where = ", ".join(str(d) for d in weight_directories(explicit))
    for variant, spec in VARIANTS.items():
        files = find_weights(variant, explicit)
        if files is None:
            notes.append(
                f"LPIPS-{variant} skipped: needs {spec['linear']} and {spec['backbone_glob']} "
                f"in {where} (nothing is downloaded)"
            )
        else:
            found[variant] = Lpips(variant, *files)
    return found, notes
