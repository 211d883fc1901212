"""One calibrated pair reconstructed: rectify, match (SGBM), triangulate (files: `dstereo.jobs.reconstruct`).

Calibrated path (here): Bouguet rectification in JAX (`dstereo.stereo.rectify`), images resampled by `cv2.remap`
on maps computed in JAX, SGBM disparity (`dstereo.stereo.matching`), optionally refined to sub-pixel accuracy
(`dstereo.stereo.subpixel`: the originals resampled again by cubic B-spline at the exact map positions,
Lucas-Kanade along the rows; `refine`), points from Q in the original left camera frame (mm,
`dstereo.stereo.points_from_disparity`). A Middlebury-style calibration of an already rectified pair skips the
resampling. Uncalibrated path: `dstereo.stereo.uncalibrated`. `dstereo.jobs.reconstruct.run_reconstruction` reads the
files and writes the results folder. Library functions return results and warnings; they never print.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.stereo.disparity import SGBMParams
from dstereo.stereo.density_check import checked_density
from dstereo.stereo.matching import initial_range, match_in_range, sized_sgbm, user_sgbm_names
from dstereo.stereo.pair_result import PairResult, calibration_size_check, check_pair, check_rig, grey
from dstereo.stereo.points_from_disparity import LOW_DENSITY, points_and_summary
from dstereo.config.reconstruction_config import ReconstructionConfig
from dstereo.stereo.uncalibrated import reconstruct_uncalibrated, uncalibrated_q

# Names the commands, tests and experiments import from here (the pipeline's public face).
__all__ = [
    "LOW_DENSITY", "PairResult", "ReconstructionConfig", "RectifyingMaps", "add_uncertainty", "check_pair",
    "disparity_sigma_hook", "initial_range", "match_in_range", "reconstruct_calibrated",
    "reconstruct_uncalibrated", "rectifying_maps", "sized_sgbm", "uncalibrated_q",
    "user_sgbm_names",
]


@dataclass(frozen=True)
class RectifyingMaps:
    """A calibration's rectification at one image size and what resamples its pairs: the exact float64 maps
    (left, right; the sub-pixel refinement's) and their float32 copies for cv2.remap (None for an already
    rectified pair), and the rectified pixels whose source lies outside the image. The same for every pair of a
    sequence: `dstereo recession` makes them once (`rectifying_maps`) and passes them to each frame."""

    rect: object
    exact: list | None
    remap: list | None
    outside: np.ndarray


def rectifying_maps(calib: StereoCalibration, size: tuple[int, int],
                    config: ReconstructionConfig = ReconstructionConfig()) -> RectifyingMaps:
    """The rectification of `calib` for (width, height) images and its maps (`RectifyingMaps`)."""
    from dstereo.stereo.rectify import rectified_from_projections
    from dstereo.stereo.rectify_fisheye import rectification_maps, rectify_any

    check_rig(calib)  # a rig with |T| ~ 0 would be blamed below for a vertical baseline
    if calib.rectified:
        rect = rectified_from_projections(*calib.projections(), size)
        outside = np.zeros((size[1], size[0]), bool)
        outside.flags.writeable = False
        return RectifyingMaps(rect, None, None, outside)
    rect = rectify_any(calib, size, alpha=config.alpha, zero_disparity=config.zero_disparity,
                       undistort=config.undistort, projection=config.rectification)  # rectify_fisheye's rule
    if rect.vertical:
        raise DstereoError(
            f"calibration {calib.source}: the baseline is vertical; SGBM matches along rows, so rotate both "
            "images (and the calibration) by 90 degrees"
        )
    exact_maps = rectification_maps(calib, rect)  # NaN where a ray has no source pixel (fisheye pairs)
    mx, my = exact_maps[0]
    outside = ~((mx >= 0) & (my >= 0) & (mx <= size[0] - 1) & (my <= size[1] - 1))  # NaN counts as outside
    remap = [tuple(np.nan_to_num(m, nan=-1e6).astype(np.float32) for m in pair) for pair in exact_maps]
    maps = RectifyingMaps(rect, exact_maps, remap, outside)
    for array in (outside, *(m for pair in maps.exact + maps.remap for m in pair)):
        array.flags.writeable = False  # shared by every pair they resample
    return maps


def reconstruct_calibrated(calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                           config: ReconstructionConfig = ReconstructionConfig(), name: str = "pair",
                           maps: RectifyingMaps | None = None) -> PairResult:
    """Rectify (unless already rectified), SGBM, and triangulate one pair with a stereo calibration. `maps`:
    `rectifying_maps(calib, size, config)` made once for many pairs (default: made here)."""
    import cv2

    from dstereo.stereo.rectify_fisheye import has_fisheye

    check_pair(left, right, calib)
    size = (left.shape[1], left.shape[0])
    unchecked = calibration_size_check(calib, size)  # a file without imageSize: refused if evidently other images
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if maps is None:
        maps = rectifying_maps(calib, size, config)
    elif maps.outside.shape != left.shape[:2]:
        raise ValueError(f"maps for {maps.outside.shape[1]}x{maps.outside.shape[0]} images given for a "
                         f"{size[0]}x{size[1]} pair")
    rect, exact_maps, outside = maps.rect, maps.exact, maps.outside
    if maps.remap is None:
        left_rect, right_rect = left, right
    else:
        left_rect, right_rect = (cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                                 for img, (mx, my) in zip((left, right), maps.remap))
    timings["rectify_s"] = time.perf_counter() - t0
    Q = np.asarray(rect.Q)
    t0 = time.perf_counter()
    disparity, params, search_range, warnings = match_in_range(name, left_rect, right_rect, config, Q, outside,
                                                               calib=calib)
    timings["disparity_s"] = time.perf_counter() - t0
    matrices = {k: np.asarray(getattr(rect, k)) for k in ("R1", "R2", "P1", "P2", "Q", "roi1", "roi2")}
    matrices["projection"] = np.array(rect.projection)  # how P1, P2 map a ray (`rectify.Rectification`)
    matrices["size"] = np.array(rect.size)
    # calibration_unit: the unit the calibration file was in (converted to mm here), or that mm was assumed
    summary = {"mode": "calibrated", "calibration": calib.source, "calibration_unit": calib.unit_note,
               "units": "mm", "scaled": True,
               "frame": "original left camera (x right, y down, z forward); pixel grid of the rectified left image",
               "sgbm": params.as_dict(), "search_range": search_range, "alpha": config.alpha,
               "zero_disparity": config.zero_disparity, "refine": {"enabled": False},
               "rectification": {"projection": rect.projection, "why": rect.why or (
                   "already rectified: the calibration's P1, P2" if calib.rectified else
                   "a pinhole pair: Bouguet's rectification (cv2.stereoRectify)")}}
    if not calib.rectified and (has_fisheye(calib) or rect.projection != "pinhole"):
        from dstereo.stereo.rectify_fisheye import field_of_view

        summary |= {"lenses": list(calib.models), "rectified_field_of_view_deg": field_of_view(rect),
                    "balance": config.alpha if config.alpha >= 0 else 0.0}
    disparity, filled, fill_sigma, exact = checked_density(name, left, right, left_rect, right_rect, exact_maps,
                                                           disparity, params, Q, outside, config, summary, timings,
                                                           warnings)  # refined, filled, the density check
    result = points_and_summary(name, left_rect, right_rect, disparity, Q, np.asarray(rect.R1), config, matrices, summary,
                                timings, warnings, filled, fill_sigma)
    result.exact_rect = exact
    if unchecked:
        result.warnings.append(unchecked)
    if config.uncertainty:
        add_uncertainty(result, calib, config, params, originals=(left, right),
                        disparity_only=not calib.rectified and (has_fisheye(calib) or rect.projection != "pinhole"))
    reach = beyond_corner_reach(result.points, calib)
    if reach is not None:
        result.summary["corner_reach"] = reach
        if reach["beyond"]:
            result.warnings.append(
                f"{name}: {reach['beyond']} of {reach['points']} points ({100 * reach['beyond_share']:.1f} %) lie "
                f"beyond the widest angle the calibration's corners reached (left {_deg(reach['left_deg'])}, right "
                f"{_deg(reach['right_deg'])} off each axis): there the lens model is extrapolated, not measured, and "
                "their +- is a lower bound (summary corner_reach); add calibration views that reach those parts")
    return result


def _deg(v) -> str:
    return "unknown" if v is None else f"{v:.0f} deg"


def beyond_corner_reach(points: np.ndarray, calib: StereoCalibration) -> dict | None:
    """How many reconstructed points (left camera frame, (..., 3), NaN where none) lie farther off either camera's
    axis than its calibration's corners reached (stereo.yml's corner_angle_max1/2, degrees; the right camera's
    point R p + T): beyond, the lens model was extrapolated, not measured (the projection maps' corners' field, seen
    as the cone it spans). None when the file records neither angle or no point was made."""
    reach = [calib.extras.get(f"corner_angle_max{i}") for i in (1, 2)]
    reach = [float(r) if isinstance(r, float) else None for r in reach]
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if all(r is None for r in reach) or not len(p):
        return None
    beyond = np.zeros(len(p), bool)
    out = {"left_deg": reach[0], "right_deg": reach[1], "points": int(len(p))}
    for side, pts, r in (("left", p, reach[0]),
                         ("right", p @ np.asarray(calib.R, float).T + np.asarray(calib.T, float).reshape(3), reach[1])):
        if r is None:
            continue
        angle = np.degrees(np.arccos(np.clip(pts[:, 2] / np.linalg.norm(pts, axis=1), -1.0, 1.0)))
        out[f"beyond_{side}"] = int(np.sum(angle > r))
        beyond |= angle > r
    out["beyond"], out["beyond_share"] = int(beyond.sum()), float(beyond.mean())
    return out


# Why a rig with a fisheye (or a spherical rectification) gets the disparity noise's sigmas alone.
FISHEYE_NOTE = ("calibration uncertainty not propagated through a fisheye lens or a spherical rectification yet (the "
                "propagation re-rectifies pinhole lenses to a pinhole pair): the point sigmas cover the disparity "
                "noise only")


def add_uncertainty(result: PairResult, calib: StereoCalibration, config: ReconstructionConfig,
                    params: SGBMParams | None = None, originals=None, disparity_only: bool = False) -> PairResult:
    """Fill `result.uncertainty` and summary['uncertainty'] (see `dstereo.uncertainty.points`) with the
    per-pixel disparity noise of `disparity_sigma_hook`; `disparity_only` (a rig with a fisheye): that noise's
    part alone (`disparity_covariances`, through the rectification's own projection), with a warning."""
    from dstereo.uncertainty.points import disparity_covariances, point_covariances

    t0 = time.perf_counter()
    sigma_d, source = disparity_sigma_hook(result, config, params, originals)
    if result.filled is not None and result.filled.any():  # a filled pixel's sigma is its fit's (`stereo.fill`)
        sigma_d = np.where(result.filled, result.fill_sigma, np.broadcast_to(sigma_d, result.filled.shape))
        source += "; filled pixels: the fill's own sigma (dstereo.stereo.fill)"
    if disparity_only:
        result.uncertainty = disparity_covariances(result, sigma_d, FISHEYE_NOTE, full=config.full_covariance,
                                                   sigma_d_source=source)
    else:
        result.uncertainty = point_covariances(calib, result, sigma_d, full=config.full_covariance,
                                               sigma_d_source=source)
    result.summary["uncertainty"] = result.uncertainty.summary()
    result.summary.setdefault("timings_s", {})["uncertainty_s"] = time.perf_counter() - t0
    if disparity_only:
        result.warnings.append(f"{result.name}: {FISHEYE_NOTE}")
    elif not result.uncertainty.calibration_included:
        result.warnings.append(f"{result.name}: calibration uncertainty not included ({calib.source} has no "
                               "covariance); the point sigmas cover disparity noise only")
    return result


def disparity_sigma_hook(result: PairResult, config: ReconstructionConfig, params: SGBMParams | None = None,
                         originals=None, report_image_noise: bool = True):
    """(sigma_d (h, w) px, source) of the result's disparity: the per-pixel model of `dstereo.stereo.disparity_noise`
    (or the configured constant), its level set by the scatter on smooth parts of the map (plane check);
    the check goes to summary['disparity_noise'], its warnings to the result's. `report_image_noise` False:
    the originals' own noise (reported only) is not estimated."""
    from dstereo.stereo.disparity_noise import disparity_sigma_map

    refined = result.exact_rect is not None
    rectified = result.exact_rect if refined else tuple(grey(x).astype(np.float64) for x in
                                                        (result.left_rect, result.right_rect))
    originals = originals if originals is not None else (result.left_rect, result.right_rect)
    block = (params or config.sgbm).block_size
    matched = result.disparity if result.filled is None else np.where(result.filled, np.nan, result.disparity)
    sigma, info, warnings = disparity_sigma_map(originals, rectified, matched, refined, block,
                                                config.disparity_sigma, result.name,
                                                report_image_noise=report_image_noise)
    result.summary["disparity_noise"] = info
    result.warnings.extend(warnings)
    return sigma, info["basis"] + (f"; scaled by {info['scaled_by']:.3g} by the plane check"
                                   if info["scaled_by"] != 1.0 else "")
