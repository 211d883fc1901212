"""Metric scale of an unscaled (uncalibrated, thesis 4.2.2.4) reconstruction from a reference of known size.

An uncalibrated PairResult is known up to a scale (its baseline is 1 unless one was given); the factor that
makes a known object come out at its known size, times its points, gives millimetres. Sphere: a geometric sphere
fit (Gauss-Newton on |p - c| - r) of the facing, inlying points; Distances (or a board's neighbouring corners):
marked pixels on the reconstruction's pixel grid, their points' distances against the known ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dstereo.errors import DstereoError
from dstereo.reference.objects import Board, Distances, Sphere
from dstereo.reference.sphere_fit import LIMB_DEG, facing, fit_sphere, sphere_inliers


@dataclass(frozen=True)
class MetricScale:
    """Multiply the reconstruction's points by `factor` (std `std`) for millimetres."""

    factor: float
    std: float
    reference: str
    n: int  # points (sphere) or distances used
    residual_rms: float  # of the fit, in the reconstruction's unit


def board_distances(board: Board) -> Distances:
    """Every pair of neighbouring inner corners of `board` (row and column neighbours), one square apart."""
    cols, rows = board.pattern
    idx = np.arange(cols * rows).reshape(rows, cols)
    pairs = np.concatenate([np.c_[idx[:, :-1].ravel(), idx[:, 1:].ravel()], np.c_[idx[:-1].ravel(), idx[1:].ravel()]])
    return Distances(pairs, np.full(len(pairs), float(board.square)))


def _sphere_scale(points: np.ndarray, sphere: Sphere) -> MetricScale:
    keep = sphere_inliers(points)
    c, r = fit_sphere(points[keep])
    keep &= facing(points, c, [np.zeros(3)], LIMB_DEG)
    p = points[keep]
    if len(p) < 20:
        raise DstereoError(f"metric scale: only {len(p)} points lie on a sphere; check the reconstruction")
    x = np.r_[fit_sphere(p)]
    for _ in range(20):  # Gauss-Newton on the geometric distance
        d = p - x[:3]
        n = np.linalg.norm(d, axis=1)
        J = np.c_[-d / n[:, None], -np.ones(len(p))]
        step = np.linalg.lstsq(J, -(n - x[3]), rcond=None)[0]
        x = x + step
        if np.max(np.abs(step)) <= 1e-12 * x[3]:
            break
    res = np.linalg.norm(p - x[:3], axis=1) - x[3]
    cov = np.linalg.inv(J.T @ J) * (res @ res) / (len(p) - 4)
    factor = sphere.radius / x[3]
    return MetricScale(float(factor), float(factor * np.sqrt(cov[3, 3]) / x[3]), "sphere", len(p),
                       float(np.sqrt(np.mean(res**2))))


def _distance_scale(points: np.ndarray, dist: Distances, marks: np.ndarray) -> MetricScale:
    if points.ndim != 3:
        raise DstereoError("metric scale from marks needs the (h, w, 3) point grid of the reconstruction")
    h, w = points.shape[:2]
    uv = np.rint(np.asarray(marks, float)).astype(int)
    if np.any(uv < 0) or np.any(uv[:, 0] >= w) or np.any(uv[:, 1] >= h):
        raise DstereoError(f"metric scale: a mark lies outside the {w}x{h} reconstruction grid")
    p = points[uv[:, 1], uv[:, 0]]
    pairs, lengths = np.asarray(dist.pairs), np.asarray(dist.lengths, float)
    m = np.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1)
    ok = np.isfinite(m)
    if ok.sum() < 2:
        raise DstereoError("metric scale: fewer than 2 known distances have a reconstructed point at both ends")
    m, lengths = m[ok], lengths[ok]
    factor = float(lengths @ m / (m @ m))
    res = lengths - factor * m
    std = float(np.sqrt(res @ res / (len(m) - 1) / (m @ m)))
    return MetricScale(factor, std, "distances", int(ok.sum()), float(np.sqrt(np.mean((res / factor) ** 2))))


def metric_scale(points: np.ndarray, reference, marks: np.ndarray | None = None) -> MetricScale:
    """Scale factor (with its std) that brings `points` (an unscaled PairResult's (h, w, 3) grid, or (n, 3)) to
    the known size of `reference`: a Sphere (seen in the points), or Distances / a Board whose marked points /
    inner corners `marks` (m, 2) are pixels of the points' grid (the rectified left image)."""
    points = np.asarray(points, float)
    if isinstance(reference, Sphere):
        flat = points.reshape(-1, 3)
        return _sphere_scale(flat[np.all(np.isfinite(flat), axis=1)], reference)
    if isinstance(reference, Board):
        reference = board_distances(reference)
    if isinstance(reference, Distances):
        if marks is None:
            raise DstereoError("metric scale from distances or a board needs the marked pixels (marks)")
        return _distance_scale(points, reference, marks)
    raise DstereoError(f"metric scale: reference {type(reference).__name__} is not a Sphere, Board or Distances")
