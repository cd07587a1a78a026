"""The background colour a subject's images are composited on: named on the command line
(``white``, ``black`` or ``R,G,B``), detected from the data, and checked against it.

VHAP exports on white or black (``--background-color``); the foreground masks tell which
pixels are the subject. Detection reads up to :data:`DETECTION_FRAMES` training frames
spread over the sequence, takes every pixel whose mask is below :data:`MASK_EMPTY` and
returns the per-channel median colour of those pixels. Tolerances:

- a requested colour contradicts the data when some channel differs from the detected
  one by more than :data:`TOLERANCE` (about 13 of 255 levels: far above the noise of
  resampled or compressed frames, far below any colour one would choose instead);
- fewer than :data:`UNIFORM_FRACTION` of the background pixels within :data:`TOLERANCE`
  of the median means the background is not one colour (a scene, a mask that misses the
  subject): that is logged, and the median is still used.

Frames without background pixels (the subject fills every frame) give no detection: a
requested colour is then taken as it is, otherwise :data:`DEFAULT_BACKGROUND` (white,
FORMATS.md's default), each with a log line.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from urhead.data.layout import DatasetError
from urhead.errors import InvalidArgumentError

log = logging.getLogger("urhead.data")

NAMED_COLOURS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
DEFAULT_BACKGROUND = NAMED_COLOURS["white"]
MASK_EMPTY = 0.02
"""Mask values below this count as background (≈ 5/255: a matte's faint tail is
still background within 2 %)."""
TOLERANCE = 0.05
"""Largest per-channel difference, in [0, 1], between colours that count as the same."""
UNIFORM_FRACTION = 0.9
DETECTION_FRAMES = 8

Colour = tuple[float, float, float]


def parse_background(text: str) -> Colour:
    """``white``, ``black`` or ``R,G,B`` (three numbers in 0–255) → RGB in [0, 1]."""
    name = str(text).strip().lower()
    if name in NAMED_COLOURS:
        return NAMED_COLOURS[name]
    match = re.fullmatch(r"\s*([\d.]+)\s*,\s*([\d.]+)\s*,\s*([\d.]+)\s*", name)
    values = None
    if match is not None:
        try:
            values = [float(v) for v in match.groups()]
        except ValueError:
            values = None
    if values is None or not all(math.isfinite(v) and 0 <= v <= 255 for v in values):
        raise InvalidArgumentError(
            f"--background must be white, black or R,G,B with each in 0-255, got {text!r}"
        )
    return tuple(v / 255.0 for v in values)


def colour_name(colour) -> str:
    """``white``, ``black`` or ``R,G,B`` (0–255, rounded) for messages and logs."""
    rgb = tuple(float(c) for c in colour)
    for name, named in NAMED_COLOURS.items():
        if rgb == named:
            return name
    return ",".join(str(round(c * 255)) for c in rgb)


@dataclass(frozen=True)
class Detection:
    """What the pixels outside the masks say."""

    colour: Colour | None
    """Median RGB in [0, 1] of the background pixels; None when there were none."""
    pixels: int
    frames: int
    uniform: float
    """Fraction of the background pixels within :data:`TOLERANCE` of ``colour``."""

    def describe(self) -> str:
        return (
            f"{colour_name(self.colour)} (median of {self.pixels} pixels outside the masks "
            f"of {self.frames} frames)"
        )


def detect_background(frames: Sequence, count: int = DETECTION_FRAMES) -> Detection:
    """The background of ``frames`` (a :class:`~urhead.data.FrameSequence` or a list of
    frames with ``image`` (H, W, 3) and ``mask`` (H, W)), from ``count`` of them spread
    evenly over the sequence."""
    n = len(frames)
    picks = sorted({int(i) for i in np.linspace(0, n - 1, min(count, n)).round()}) if n else []
    pixels = []
    for i in picks:
        frame = frames[i]
        pixels.append(frame.image[frame.mask < MASK_EMPTY])
    found = torch.cat(pixels) if pixels else torch.zeros(0, 3)
    if found.shape[0] == 0:
        return Detection(None, 0, len(picks), 0.0)
    median = found.median(dim=0).values
    close = ((found - median).abs().amax(dim=1) <= TOLERANCE).float().mean()
    return Detection(tuple(float(c) for c in median), found.shape[0], len(picks), float(close))


def subject_background(
    subject, requested=None, *, requested_by: str = "--background"
) -> torch.Tensor:
    """(3,) float32 background colour of ``subject``: ``requested`` (a colour, or a string
    for :func:`parse_background`) after checking it against the data, else the detected
    colour, else :data:`DEFAULT_BACKGROUND`. A requested colour the data contradicts is a
    :class:`~urhead.data.DatasetError` naming the subject and ``requested_by`` (what asked
    for the colour)."""
    if isinstance(requested, str):
        requested = parse_background(requested)
    frames = subject.train if len(subject.train) else subject.test
    found = detect_background(frames)
    if found.colour is not None and found.uniform < UNIFORM_FRACTION:
        log.warning(
            "%s: only %.0f%% of the pixels outside the masks are within %.2f of their "
            "median %s: the background is not one colour",
            subject.root,
            100 * found.uniform,
            TOLERANCE,
            colour_name(found.colour),
        )
    if requested is not None:
        requested = tuple(float(c) for c in requested)
        if found.colour is None:
            log.info(
                "%s: no pixels outside the masks to check %s %s against; using it",
                subject.root,
                requested_by,
                colour_name(requested),
            )
        elif max(abs(a - b) for a, b in zip(requested, found.colour, strict=True)) > TOLERANCE:
            raise DatasetError(
                subject.root,
                f"{requested_by} {colour_name(requested)} contradicts the data: its background "
                f"is {found.describe()}; pass --background {colour_name(found.colour)} "
                "(or leave it out to use the detected colour)",
            )
        colour = requested
    elif found.colour is None:
        colour = DEFAULT_BACKGROUND
        log.info(
            "%s: no pixels outside the masks to detect the background from; using the default %s",
            subject.root,
            colour_name(colour),
        )
    else:
        colour = found.colour
        log.info("%s: background %s", subject.root, found.describe())
    return torch.tensor(colour, dtype=torch.float32)
