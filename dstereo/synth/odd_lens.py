"""A lens no parametric model has, and chessboard corners seen through it (numpy only, no rendering).

The lens is an equidistant fisheye (r = f theta) whose pixels are then pushed by a smooth field that is neither
radial nor tangential: a wave across the image, dx = A sin(pi (v - cy) / cy), dy = A sin(pi (u - cx) / cx) / 2
(one wavelength over the image height and width). OpenCV's models (radial polynomials or ratios, and tangential
terms of second order) and cv2.fisheye's odd polynomial in theta cannot follow it; a smooth correction surface can.
Corners are synthesised directly (exact projection plus Gaussian noise), which is all a calibration test needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.models.pose import rotation_matrix


@dataclass(frozen=True)
class OddLens:
    f: float = 420.0
    image_size: tuple[int, int] = (640, 480)
    wave_px: float = 2.0  # the field's amplitude A

    @property
    def centre(self) -> np.ndarray:
        w, h = self.image_size
        return np.array([(w - 1) / 2.0, (h - 1) / 2.0])

    def project(self, p: np.ndarray) -> np.ndarray:
        """Camera-frame points (n, 3) -> pixels (n, 2)."""
        p = np.asarray(p, float)
        rho = np.linalg.norm(p[:, :2], axis=1)
        theta = np.arctan2(rho, p[:, 2])
        direction = p[:, :2] / np.maximum(rho, 1e-300)[:, None]
        q = self.centre + self.f * theta[:, None] * direction
        c = self.centre
        wave = np.stack([self.wave_px * np.sin(np.pi * (q[:, 1] - c[1]) / c[1]),
                         0.5 * self.wave_px * np.sin(np.pi * (q[:, 0] - c[0]) / c[0])], axis=1)
        return q + wave


def board_points(cols: int, rows: int, square: float) -> np.ndarray:
    """(cols rows, 3) inner corners of a planar board (`models.board.Board`'s order), z = 0."""
    from dstereo.models.board import Board

    return np.asarray(Board(cols, rows, square).object_points(), float)


def views(lens: OddLens, obj: np.ndarray, n_views: int, seed: int = 0, noise_px: float = 0.1,
          region: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0), margin_px: float = 4.0):
    """(n_views, n, 2) noisy corners of random board poses whose corners all fall inside `region` (u0, v0, u1, v1
    as fractions of the image) and `margin_px` inside the image; rejection sampling, reproducible by `seed`."""
    rng = np.random.default_rng(seed)
    w, h = lens.image_size
    lo = np.array([region[0] * (w - 1), region[1] * (h - 1)]) + margin_px
    hi = np.array([region[2] * (w - 1), region[3] * (h - 1)]) - margin_px
    centre = obj.mean(axis=0)
    out = []
    for _ in range(200000):
        if len(out) == n_views:
            break
        rot = np.asarray(rotation_matrix(rng.normal(0.0, 0.45, 3)), float)
        # aim the board's centre along a random ray of the wanted region, at a random distance
        target = rng.uniform(lo, hi)
        d = (target - lens.centre) / lens.f  # the equidistant lens's angle and azimuth of that pixel
        theta = np.linalg.norm(d)
        ray = np.array([*(np.sin(theta) * d / max(theta, 1e-12)), np.cos(theta)])
        t = ray * rng.uniform(0.6, 1.6) * np.ptp(obj[:, 0]) * 1.2 - rot @ centre
        p = obj @ rot.T + t
        if np.any(p[:, 2] <= 0.05 * np.ptp(obj[:, 0])):
            continue
        q = lens.project(p)
        if np.all((q >= lo) & (q <= hi)):
            out.append(q + rng.normal(0.0, noise_px, q.shape))
    if len(out) < n_views:
        raise RuntimeError(f"odd_lens.views: found only {len(out)} of {n_views} poses inside {region}")
    return np.stack(out)
