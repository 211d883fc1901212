"""Start for a fisheye calibration, numpy only: the equidistant lens (r = f theta) that best explains the views.

Zhang's start fits a homography to the distorted corners, which a wide lens bends far from any homography.
Here, for each trial focal f (principal point at the image centre), the corners are undistorted through the
equidistant model, a homography is fitted per view to the undistorted points, and the board points are mapped
back through it and the same model to pixels; the f whose reprojection error is smallest wins (a log-spaced
scan, then a finer one around the best). Each view's pose then comes from its homography with K = I.
"""

from __future__ import annotations

import numpy as np

from dstereo.calib.init_zhang import homography, pose_from_homography
from dstereo.errors import DstereoError

# Trial focal lengths as multiples of the image width: w / 6 (beyond 180 degrees across the width) to 3 w (a
# 19-degree lens); a scan of 48 values is ~7 % apart, then a second scan of 48 across the best two intervals.
F_RANGE = (1.0 / 6.0, 3.0)
F_STEPS = 48


def _equidistant_undistort(uv: np.ndarray, f: float, c: np.ndarray) -> np.ndarray | None:
    d = (uv - c) / f
    theta = np.linalg.norm(d, axis=-1)
    if np.any(theta >= 1.45):  # within ~83 degrees of the axis the homography fit stays well conditioned
        return None
    scale = np.where(theta > 1e-12, np.tan(theta) / np.maximum(theta, 1e-12), 1.0)
    return d * scale[..., None]


def _equidistant_project(xy: np.ndarray, f: float, c: np.ndarray) -> np.ndarray:
    r = np.linalg.norm(xy, axis=-1)
    scale = np.where(r > 1e-12, np.arctan(r) / np.maximum(r, 1e-12), 1.0)
    return c + f * xy * scale[..., None]


def _fit(obj2: np.ndarray, obs: np.ndarray, f: float, c: np.ndarray):
    """Median per-view RMS (px) of the equidistant + homography fit at focal f, and the homographies."""
    xy = _equidistant_undistort(obs, f, c)
    if xy is None:
        return np.inf, None
    hs, errs = [], []
    for o, x in zip(obs, xy):
        h = homography(obj2, x)
        m = np.column_stack([obj2, np.ones(len(obj2))]) @ h.T
        if np.any(m[:, 2] * np.sign(np.mean(m[:, 2])) <= 0):  # the board would cross the camera plane
            return np.inf, None
        back = _equidistant_project(m[:, :2] / m[:, 2:], f, c)
        errs.append(np.sqrt(np.mean(np.sum((back - o) ** 2, axis=1))))
        hs.append(h)
    return float(np.median(errs)), hs


def initial_guess_fisheye(obj: np.ndarray, obs: np.ndarray, image_size: tuple[int, int]):
    """obj (n, 3) planar z = 0 board, obs (V, n, 2) -> k (4,) = (f, f, cx, cy) and poses (V, 6)."""
    w = float(image_size[0])
    c = np.array([(image_size[0] - 1) / 2.0, (image_size[1] - 1) / 2.0])
    obj2 = np.asarray(obj, float)[:, :2]
    grid = w * np.geomspace(*F_RANGE, F_STEPS)
    costs = [_fit(obj2, obs, f, c)[0] for f in grid]
    i = int(np.argmin(costs))
    if not np.isfinite(costs[i]):
        raise DstereoError("calibration start (fisheye): no equidistant focal length between "
                           f"{grid[0]:.0f} and {grid[-1]:.0f} px fits the board views; check `pattern` and the images")
    fine = np.geomspace(grid[max(i - 1, 0)], grid[min(i + 1, F_STEPS - 1)], F_STEPS)
    costs = [_fit(obj2, obs, f, c)[0] for f in fine]
    f = float(fine[int(np.argmin(costs))])
    _, hs = _fit(obj2, obs, f, c)
    poses = np.stack([pose_from_homography(h, np.eye(3)) for h in hs])
    return np.array([f, f, c[0], c[1]]), poses
