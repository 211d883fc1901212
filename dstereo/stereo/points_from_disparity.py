"""A matched pair's disparity to points in the left camera frame, with the ROI, outlier removal, density
check and the pair's summary."""

from __future__ import annotations

import time

import numpy as np

from dstereo.errors import DstereoError
from dstereo.stereo.matching import require_disparity
from dstereo.stereo.pair_result import PairResult
from dstereo.stereo.point_outliers import remove_statistical_outliers
from dstereo.config.reconstruction_config import ReconstructionConfig

LOW_DENSITY = 0.10  # below this valid fraction the result carries a warning


def points_and_summary(name, left_rect, right_rect, disparity, Q, R1, config: ReconstructionConfig, matrices, summary,
                       timings, warnings, filled=None, fill_sigma=None) -> PairResult:
    """Disparity -> points in the left frame, ROI, outliers, density checks and the summary. `filled` (h, w) bool:
    the pixels whose disparity a fill gave (`dstereo.stereo.fill`, with `fill_sigma` px), counted apart."""
    from dstereo.stereo.triangulate import reproject, to_original_left

    t0 = time.perf_counter()
    if not summary["refine"]["enabled"]:  # refined: checked on SGBM's map before the refinement
        require_disparity(name, disparity if filled is None else np.where(filled, np.nan, disparity), summary)
    rect = {"Q": Q, **matrices}  # a spherical rectification's matrices say so (`projection`); else through Q
    points = np.array(to_original_left(reproject(disparity.astype(np.float64), rect), R1))  # writable
    if config.roi is not None:
        x, y, w, h = config.roi
        keep = np.zeros(disparity.shape, bool)
        keep[max(y, 0): y + h, max(x, 0): x + w] = True
        if not keep.any():
            raise DstereoError(f"roi {config.roi} lies outside the {disparity.shape[1]}x{disparity.shape[0]} "
                               "rectified image; give x, y, w, h inside it")
        points[~keep] = np.nan
    if config.outlier_neighbours > 0:
        points = remove_statistical_outliers(points, config.outlier_neighbours, config.outlier_std)
    valid = np.all(np.isfinite(points), axis=2)
    disparity = np.where(valid, disparity, np.nan).astype(np.float32)
    depth = np.where(valid, points[..., 2], np.nan)
    if filled is not None:
        filled = filled & valid
        fill_sigma = np.where(filled, fill_sigma, np.nan)
        summary["fill"] |= {"filled_points": int(filled.sum()), "matched_points": int((valid & ~filled).sum()),
                            "filled_share": float(filled.sum() / max(valid.sum(), 1))}
    timings["triangulate_s"] = time.perf_counter() - t0
    fraction = float(valid.mean())
    if fraction == 0:  # the results folder is still written whole: points.ply and mesh.ply valid and empty
        warnings.append(f"{name}: no pixel has a point (every disparity is invalid or removed); points.ply and "
                        "mesh.ply are written empty; check disparity.png, the depth range (--z-min/--z-max) and "
                        "the outlier settings")
    elif fraction < LOW_DENSITY:
        warnings.append(
            f"{name}: only {100 * fraction:.1f}% of pixels have a point; add texture to the scene, set the depth "
            "range (--z-min/--z-max), or lower --sgbm uniqueness_ratio"
        )
    z = depth[valid]
    summary.update({
        "name": name,
        "image_size": [int(disparity.shape[1]), int(disparity.shape[0])],
        "valid_fraction": fraction,
        "valid_points": int(valid.sum()),
        "depth_mm": {"min": float(z.min()), "max": float(z.max()), "median": float(np.median(z)),
                     "p05": float(np.percentile(z, 5)), "p95": float(np.percentile(z, 95))} if z.size else None,
        "disparity_px": {"min": float(np.nanmin(disparity)), "max": float(np.nanmax(disparity))} if z.size else None,
        "timings_s": timings,
        "warnings": warnings,
    })
    colors = left_rect[..., ::-1] if left_rect.ndim == 3 else np.repeat(left_rect[..., None], 3, axis=2)
    return PairResult(name, left_rect, right_rect, disparity, depth, points, np.ascontiguousarray(colors),
                      matrices, summary, warnings, filled=filled, fill_sigma=fill_sigma)
