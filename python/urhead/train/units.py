"""The fit works in metres: its epsilons, learning rates and regularisers are stated in
metres (``depth_eps`` 1 cm, the displacement and offset rates, the Laplacian and offset
weights, the Gaussians' initial scales). Rather than rescale each of them, a subject in
other units is refused before any work, with the unit it should be in (NUMERICS.md case 28).

Two lengths give the unit away: the head model's size, and the camera's distance from the
head. Both ranges are wide enough for any real head and capture, and a factor of 1000 (mm,
km) outside them.
"""

from __future__ import annotations

import numpy as np

from urhead.errors import UnitsError

HEAD_EXTENT = (0.1, 2.0)
"""metres: the diagonal of the head template's bounding box (FLAME and the built-in
head: 0.44 m, neck included)."""
CAMERA_DISTANCE = (0.05, 50.0)
"""metres: from the camera centre to the head's position in a training frame."""


def check_metres(subject, head) -> None:
    """Raises :class:`UnitsError` unless ``head`` (a head model) and ``subject`` (its first
    training frame's camera and FLAME translation) are in metres."""
    extent = float(np.linalg.norm(np.ptp(np.asarray(head.v_template, np.float64), axis=0)))
    low, high = HEAD_EXTENT
    if not low <= extent <= high:
        raise UnitsError(
            f"the head model is {extent:.4g} units across; urhead works in metres, where a "
            f"head is about 0.4 m (between {low} and {high} m accepted): convert the head "
            "model and the subject's cameras and FLAME translations to metres"
        )
    record = subject.train.records[0]
    translation = subject.flame[record.flame_path]["translation"].reshape(-1)[:3]
    centre = record.camera.center.double().numpy().reshape(-1)[:3]
    distance = float(np.linalg.norm(centre - translation.astype(np.float64)))
    low, high = CAMERA_DISTANCE
    if not low <= distance <= high:
        raise UnitsError(
            f"{subject.root}: the camera is {distance:.4g} units from the head in "
            f"{record.flame_path.parent.name}/{record.flame_path.name}; urhead works in "
            f"metres (between {low} and {high} m accepted): write the cameras and FLAME "
            "translations in metres"
        )
