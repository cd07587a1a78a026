"""Side-by-side panels with a label bar above each: the labels sit on their own white bar,
so the panels' pixels stay exactly the rendered ones."""

from __future__ import annotations

import numpy as np


def label_bar_height(panel_height: int) -> int:
    """An even height (video encoders want even sizes): ~1/16 of the panel, at least 12."""
    return 2 * max(6, round(panel_height / 32))


def labelled_row(panels: list[np.ndarray], labels: list[str]) -> np.ndarray:
    """(H, W_i, 3) uint8 panels side by side under a white bar with each one's label, in
    black, centred and shrunk to fit its panel: (bar + H, ΣW_i, 3)."""
    import cv2

    if len(panels) != len(labels):
        raise ValueError(f"{len(panels)} panels but {len(labels)} labels")
    height = panels[0].shape[0]
    bar = label_bar_height(height)
    font = cv2.FONT_HERSHEY_SIMPLEX
    columns = []
    for panel, label in zip(panels, labels, strict=True):
        width = panel.shape[1]
        header = np.full((bar, width, 3), 255, np.uint8)
        scale = bar / 30
        (w, h), _ = cv2.getTextSize(label, font, scale, 1)
        if w > width - 2:
            scale *= (width - 2) / w
            (w, h), _ = cv2.getTextSize(label, font, scale, 1)
        origin = ((width - w) // 2, (bar + h) // 2)
        cv2.putText(header, label, origin, font, scale, (0, 0, 0), 1, cv2.LINE_AA)
        columns.append(np.concatenate([header, panel], 0))
    return np.concatenate(columns, 1)
