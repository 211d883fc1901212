"""A sphere fitted to triangulated points: algebraic fit, robust inliers, and the points that face the cameras."""

from __future__ import annotations

import numpy as np

def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares sphere (centre, radius) of (n, 3) points: |p|^2 = 2 c.p + (r^2 - |c|^2)."""
    a = np.c_[2 * points, np.ones(len(points))]
    sol, *_ = np.linalg.lstsq(a, np.sum(points**2, axis=1), rcond=None)
    c = sol[:3]
    return c, float(np.sqrt(sol[3] + c @ c))


def sphere_inliers(points: np.ndarray, rounds: int = 4, k: float = 5.0) -> np.ndarray:
    """Mask of points within k robust standard deviations (1.4826 MAD) of a free-radius sphere fit, refitted
    `rounds` times: drops mismatches and background before the least squares."""
    finite = np.all(np.isfinite(points), axis=1)
    keep = finite
    for _ in range(rounds):
        c, r = fit_sphere(points[keep])
        dist = np.abs(np.linalg.norm(points - c, axis=1) - r)
        keep = finite & (dist <= max(k * 1.4826 * np.median(dist[keep]), 1e-12))
    return keep


def facing(points: np.ndarray, centre: np.ndarray, camera_centres: list[np.ndarray], max_deg: float) -> np.ndarray:
    """Mask of sphere points whose outward normal is within `max_deg` of the line of sight to every camera."""
    n = (points - centre) / np.linalg.norm(points - centre, axis=1, keepdims=True)
    ok = np.ones(len(points), bool)
    for c in camera_centres:
        v = (c - points) / np.linalg.norm(c - points, axis=1, keepdims=True)
        ok &= np.sum(n * v, axis=1) >= np.cos(np.radians(max_deg))
    return ok


LIMB_DEG = 70.0  # sphere points seen more obliquely than this are dropped (see refine._sphere_problem)
