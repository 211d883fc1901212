"""Statistical outlier removal on an organised point cloud (PCL's filter): a point far from its neighbours goes."""

from __future__ import annotations

import numpy as np

from dstereo.errors import DstereoError


def remove_statistical_outliers(points: np.ndarray, neighbours: int = 16, std_ratio: float = 2.0) -> np.ndarray:
    """Copy of an organised cloud with NaN at points whose mean distance to their `neighbours` nearest points
    exceeds the mean of that statistic by `std_ratio` standard deviations (PCL's statistical filter)."""
    from scipy.spatial import cKDTree

    if neighbours < 1 or std_ratio <= 0:
        raise DstereoError(f"outlier removal: neighbours={neighbours} must be >= 1 and std_ratio={std_ratio} > 0")
    out = np.array(points, dtype=np.float64, copy=True)
    flat = out.reshape(-1, 3)
    ok = np.flatnonzero(np.all(np.isfinite(flat), axis=1))
    if len(ok) <= neighbours:
        return out
    dist, _ = cKDTree(flat[ok]).query(flat[ok], k=neighbours + 1)
    mean = dist[:, 1:].mean(axis=1)
    limit = mean.mean() + std_ratio * mean.std()
    flat[ok[mean > limit]] = np.nan
    return out
