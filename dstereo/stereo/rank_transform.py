"""The rank transform (Zabih & Woodfill 1994): each pixel replaced by how many pixels of its window are darker.
Any strictly increasing change of the grey levels (a gain, an offset, a gamma; a lens's vignetting, which is
almost constant over a window) leaves it unchanged, so SGBM's cost on the ranks survives two views lit or exposed
differently, where its cost on the grey levels does not (experiments/middlebury_lighting.py)."""

from __future__ import annotations

import numpy as np

RANK_RADIUS = 3  # a 7 x 7 window: 48 comparisons (Middlebury 2014 quarter size: denser than 5 x 5, same accuracy)


def rank_transform(grey: np.ndarray, radius: int = RANK_RADIUS) -> np.ndarray:
    """(h, w) uint8 rank image of an (h, w) uint8 grey image: 2 x (#darker) + (#equal) neighbours in the
    (2 radius + 1)^2 window (ties count half, so a flat patch is mid-grey rather than black), scaled to 0..255.
    The image edge is extended by its border pixels."""
    g = grey.astype(np.int16)
    h, w = g.shape
    padded = np.pad(g, radius, mode="edge")
    total = np.zeros((h, w), np.int16)  # at most 2 x 48 for radius 3: int16 is plenty
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy or dx:
                s = padded[radius + dy: radius + dy + h, radius + dx: radius + dx + w]
                total += (s < g).astype(np.int16) * 2 + (s == g)
    n = (2 * radius + 1) ** 2 - 1
    return np.rint(total * (255.0 / (2 * n))).astype(np.uint8)
