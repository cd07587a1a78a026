"""What a scene needs, measured from its training frames before a fit, and which parts of
the model the fit therefore leaves out.

Measured (training frames only; held-out frames never shape the model):

- the mouth: the mesh with the tracked FLAME parameters is rasterized and the pixels where
  the mouth interior or the teeth are the front surface counted — a mouth that never
  opens needs neither their faces nor their texels, but for the few faces a closed mouth
  still shows between the lips (those are kept);
- the eyes: the spread of the tracked eye poses — eyes that never move need no per-frame
  eye joints (a tracker's jitter about a fixed gaze is noise to fit, not motion);
- content off the FLAME surface: the mask pixels the rasterized mesh does not reach
  (beyond a few pixels' slack for tracking error) — reported, not a switch: the Gaussians'
  offset map E is kept without such content too, because it also fits the silhouette the
  tracked surface misses (on a hairless subject, leaving E out cost 0.08-0.29 dB refined
  and 0.11-0.16 dB on the full image in two measurements, for 1.7 % of the maps' memory);
- normal maps: whether the subject has them (the normal loss needs them).

Light that changes with head pose is not measured (the pose-driven shading maps are
only used when asked for).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from urhead.config import KEEPABLE_PARTS, FitConfig
from urhead.head import HeadModel
from urhead.head.leave_out import region_faces
from urhead.model.avatar import POSE_SIZE, FlameParams, flame_rows, head_tables, skin
from urhead.model.build import subject_identity
from urhead.ops import rasterize

log = logging.getLogger("urhead.fit")

MOUTH_REGIONS = ("mouth_interior", "teeth")
"""What a closed mouth leaves out: the inner lips, mouth bag and plate, and the teeth."""

MOUTH_OPEN_FRACTION = 2e-3
"""A frame shows an open mouth when the mouth interior or teeth are the front surface on
at least this fraction of the mesh's pixels (0.2 %: speech shows 1-4 %; a closed mouth
of the built-in head shows < 0.15 %, teeth between the lips)."""

EYE_MOTION_RAD = 0.05
"""Eyes move when a tracked eye-pose component spans more than this (5th to 95th
percentile, ~3°): saccades span ~0.5 rad; a photometric tracker's jitter about a fixed
gaze (~0.01 rad) stays well below."""

OFF_SURFACE_SLACK = 0.01
"""The mesh's reach: its coverage grown by this fraction of the image side (≥ 2 px),
the silhouette error tracking leaves."""

MOUTH_FRAMES = 256
"""Frames rasterized for the mouth, spread evenly over the training split..."""
WIDEST_JAW_FRAMES = 16
"""...plus those with the widest tracked jaw opening (a mouth opened briefly is found)."""
MOUTH_SLIVER_SHARE = 1e-4
"""Of a closed mouth, a region (mouth interior, teeth) is left out whole when it is the
front surface of under this share of the mesh's pixels (0.01 %: at most 0.02 dB at 27 dB
with colour errors of 0.3); of a region seen more (the teeth's edges between the lips)
the faces seen are kept."""
MASK_FRAMES = 64
"""Frames whose masks are compared with the mesh, spread evenly."""


@dataclass(frozen=True)
class SceneMeasures:
    """What the training frames show."""

    frames_analysed: int
    """Frames rasterized for the mouth."""
    mouth_frames: int
    """Of those, frames showing an open mouth (:data:`MOUTH_OPEN_FRACTION`)."""
    mouth_pixels_max: int
    """Most mouth-interior/teeth pixels in one analysed frame."""
    mouth_faces_seen: tuple[int, ...]
    """Mouth-interior/teeth faces a fit keeps for a closed mouth: those seen between the
    lips, of the regions seen beyond :data:`MOUTH_SLIVER_SHARE`."""
    jaw_opening_max: float
    """Largest tracked jaw opening over the training frames, radians."""
    eye_spread: float
    """Largest 5th-95th percentile span of an eye-pose component, radians."""
    off_surface_fraction: float
    """Mean fraction of the mask beyond the mesh's reach."""
    has_normals: bool

    @classmethod
    def from_dict(cls, values: dict) -> SceneMeasures:
        """The measures from :func:`scene_report`'s ``measures`` (checkpoints)."""
        return cls(**{**values, "mouth_faces_seen": tuple(values["mouth_faces_seen"])})


@dataclass(frozen=True)
class PartChoice:
    """One part of the model, used or left out, and why."""

    used: bool
    reason: str


def analyse_scene(train, head: HeadModel, has_normals: bool) -> SceneMeasures:
    """Measures the training split ``train`` (a :class:`FrameSequence`) of a subject with
    ``head``: rasterizes the mesh with the tracked parameters of up to
    ``MOUTH_FRAMES + WIDEST_JAW_FRAMES`` frames, and compares ``MASK_FRAMES`` of them with
    their masks."""
    shape, static, num_expr = subject_identity(head, train)
    flame = train.flame_params()
    rows = torch.from_numpy(flame_rows(flame, len(train), num_expr))
    pose = rows[:, num_expr : num_expr + POSE_SIZE].numpy()
    eyes = pose[:, 9:15]
    eye_spread = float((np.percentile(eyes, 95, 0) - np.percentile(eyes, 5, 0)).max())
    jaw = pose[:, 6]
    count = len(train)
    picks = np.unique(
        np.concatenate(
            [
                np.linspace(0, count - 1, min(MOUTH_FRAMES, count)).round(),
                np.argsort(-jaw, kind="stable")[:WIDEST_JAW_FRAMES],
            ]
        ).astype(np.int64)
    )
    masked = set(np.linspace(0, count - 1, min(MASK_FRAMES, count)).round().astype(int))
    tables = head_tables(head, shape, static, num_expr)
    mouth_face = torch.from_numpy(region_faces(head, MOUTH_REGIONS))
    seen = torch.zeros(head.num_faces, dtype=torch.int64)
    open_frames, mouth_max, off_surface, mesh_pixels = 0, 0, [], 0
    for index in picks:
        with torch.no_grad():
            verts, _ = skin(tables.lbs, FlameParams.from_row(rows[int(index)], num_expr))
        camera = train.records[int(index)].camera
        tri = rasterize(verts.contiguous(), tables.faces, camera).tri_id
        covered = tri >= 0
        front = tri[covered].long()
        mouth = front[mouth_face[front]]
        mesh_pixels += front.numel()
        seen += torch.bincount(mouth, minlength=head.num_faces)
        mouth_max = max(mouth_max, int(mouth.numel()))
        if mouth.numel() >= MOUTH_OPEN_FRACTION * front.numel() and mouth.numel() > 0:
            open_frames += 1
        if int(index) in masked:
            mask = train[int(index)].mask > 0.5
            slack = max(2, round(OFF_SURFACE_SLACK * max(tri.shape)))
            grown = F.max_pool2d(covered[None, None].float(), 2 * slack + 1, 1, slack)
            if mask.any():
                beyond = mask & ~(grown[0, 0] > 0)
                off_surface.append(float(beyond.sum()) / float(mask.sum()))
    return SceneMeasures(
        frames_analysed=len(picks),
        mouth_frames=open_frames,
        mouth_pixels_max=mouth_max,
        mouth_faces_seen=_beyond_slivers(head, seen, mesh_pixels),
        jaw_opening_max=float(jaw.max()),
        eye_spread=eye_spread,
        off_surface_fraction=float(np.mean(off_surface)) if off_surface else 0.0,
        has_normals=bool(has_normals),
    )


def _beyond_slivers(head: HeadModel, pixels: torch.Tensor, mesh_pixels: int) -> tuple[int, ...]:
    """The seen faces ((F,) front-surface pixel counts ``pixels``) of the mouth regions
    whose total exceeds :data:`MOUTH_SLIVER_SHARE` of ``mesh_pixels``."""
    kept = []
    for region in MOUTH_REGIONS:
        faces = torch.from_numpy(region_faces(head, (region,)))
        if int(pixels[faces].sum()) >= MOUTH_SLIVER_SHARE * mesh_pixels:
            kept += (faces & (pixels > 0)).nonzero()[:, 0].tolist()
    return tuple(sorted(kept))


def mouth_faces_left_out(head: HeadModel, measures: SceneMeasures) -> np.ndarray:
    """(F,) bool: the mouth-interior and teeth faces no analysed frame showed."""
    dropped = region_faces(head, MOUTH_REGIONS)
    dropped[list(measures.mouth_faces_seen)] = False
    return dropped


def keep_set(config: FitConfig) -> frozenset[str]:
    """The parts ``config.keep`` forces on (``all`` = every one of :data:`KEEPABLE_PARTS`)."""
    names = {name.strip() for name in config.keep.split(",") if name.strip()}
    return frozenset(KEEPABLE_PARTS) if "all" in names else frozenset(names)


def choose_parts(measures: SceneMeasures, config: FitConfig) -> dict[str, PartChoice]:
    """Which parts the fit uses, each with its reason, from the measures and the config
    (``keep`` forces a part on; a part the config switches off stays off)."""
    m = measures
    keep = keep_set(config)
    choices = {}
    if m.mouth_frames:
        choices["mouth"] = PartChoice(
            True,
            f"open: the mouth interior or teeth show in {m.mouth_frames} of "
            f"{m.frames_analysed} frames analysed (up to {m.mouth_pixels_max} px)",
        )
    elif "mouth" in keep:
        choices["mouth"] = PartChoice(True, "kept by --keep mouth (the mouth never opens)")
    else:
        choices["mouth"] = PartChoice(
            False,
            f"never open in {m.frames_analysed} frames analysed (at most "
            f"{m.mouth_pixels_max} px of mouth interior or teeth between the lips; jaw ≤ "
            f"{m.jaw_opening_max:.3f} rad): their faces and atlas rows are left out but "
            f"for the {len(m.mouth_faces_seen)} faces seen between the lips",
        )
    if m.eye_spread > EYE_MOTION_RAD:
        choices["eyes"] = PartChoice(
            True, f"the eyes move (tracked eye poses span {m.eye_spread:.3f} rad)"
        )
    elif "eyes" in keep:
        choices["eyes"] = PartChoice(True, "kept by --keep eyes (the eyes never move)")
    else:
        choices["eyes"] = PartChoice(
            False,
            f"still: tracked eye poses span only {m.eye_spread:.3f} rad (≤ "
            f"{EYE_MOTION_RAD}); the eye joints are fixed at their median",
        )
    share = f"{100 * m.off_surface_fraction:.2f} % of the mask lies beyond the mesh's reach"
    if not (config.gaussians and config.gaussian_offset):
        choices["offsets"] = PartChoice(False, f"off in the configuration ({share})")
    else:
        # Not left out for a scene without hair: E also fits the silhouette tracking misses.
        choices["offsets"] = PartChoice(True, share)
    if not m.has_normals:
        choices["normals"] = PartChoice(False, "the subject has no normal maps")
    else:
        choices["normals"] = PartChoice(
            config.normal_loss, "normal maps present" + ("" if config.normal_loss else ", off")
        )
    choices["shading"] = PartChoice(
        config.shading, "not measured: pose-driven shading is used only when asked (--shading)"
    )
    return choices


def scene_report(measures: SceneMeasures, choices: dict[str, PartChoice]) -> dict:
    """The analysis as JSON-ready data (for ``avatar.json`` and checkpoints)."""
    return {
        "measures": asdict(measures),
        "parts": {name: asdict(choice) for name, choice in choices.items()},
    }


def log_choices(choices: dict[str, PartChoice]) -> None:
    for name, choice in choices.items():
        log.info("scene: %s %s — %s", name, "used" if choice.used else "left out", choice.reason)
