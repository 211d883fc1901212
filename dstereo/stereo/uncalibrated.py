"""The uncalibrated path (thesis 4.2.2.4): SIFT matches, robust F, Hartley homographies; Q from the user's focal
length and baseline (baseline 1: unscaled), its disparity offset fitted to the sparse matches triangulated
from E = K^T F K."""

from __future__ import annotations

import time

import numpy as np

from dstereo.errors import DstereoError
from dstereo.stereo.matching import match_in_range
from dstereo.stereo.pair_result import PairResult, check_pair
from dstereo.stereo.points_from_disparity import points_and_summary
from dstereo.config.reconstruction_config import ReconstructionConfig


def uncalibrated_q(f_px: float, size, baseline: float, d_sparse: np.ndarray, z_sparse: np.ndarray) -> np.ndarray:
    """Q for a homography-rectified pair: centre principal point, focal f_px, and the disparity sign and offset
    that best fit Z = f B / (s d + doffs) to sparse depths (median fit; s = +-1 by the smaller spread)."""
    best = None
    for s in (1.0, -1.0):
        offsets = f_px * baseline / z_sparse - s * d_sparse
        spread = np.median(np.abs(offsets - np.median(offsets)))
        if best is None or spread < best[0]:
            best = (spread, s, float(np.median(offsets)))
    _, s, doffs = best
    cx, cy = (size[0] - 1) / 2.0, (size[1] - 1) / 2.0
    return np.array([[1.0, 0, 0, -cx], [0, 1.0, 0, -cy], [0, 0, 0, f_px], [0, 0, s / baseline, doffs / baseline]])


def reconstruct_uncalibrated(left: np.ndarray, right: np.ndarray, config: ReconstructionConfig,
                             name: str = "pair") -> PairResult:
    """Thesis 4.2.2.4: SIFT + robust F + Hartley rectification; Q from the focal length and baseline."""
    import cv2

    from dstereo.stereo.features import match_sift, ransac_fundamental, relative_pose
    from dstereo.stereo.rectify import focal_px, rectify_uncalibrated
    from dstereo.stereo.subpixel import homography_maps
    from dstereo.stereo.triangulate import triangulate_rays

    check_pair(left, right, None)
    size = (left.shape[1], left.shape[0])
    if config.focal_px is not None:
        f = float(config.focal_px)
    elif config.focal_mm is not None:
        f = focal_px(config.focal_mm, size[0], pixel_size_mm=config.pixel_size_mm, crop_factor=config.crop_factor)
    else:
        raise DstereoError("uncalibrated reconstruction needs the focal length: give --focal-mm with --pixel-size-mm "
                           "or --crop-factor (or --focal-px)")
    scaled = config.baseline_mm is not None
    baseline = float(config.baseline_mm) if scaled else 1.0
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    matches = match_sift(left, right, ratio=config.ratio)
    fit = ransac_fundamental(matches.left, matches.right, threshold=config.f_threshold)
    m1, m2 = matches.left[fit.inliers], matches.right[fit.inliers]
    H1, H2 = rectify_uncalibrated(m1, m2, fit.F, size, threshold=0)
    exact_maps = (homography_maps(H1, size), homography_maps(H2, size))
    left_rect = cv2.warpPerspective(left, H1, size, flags=cv2.INTER_LINEAR)
    right_rect = cv2.warpPerspective(right, H2, size, flags=cv2.INTER_LINEAR)
    K = np.array([[f, 0.0, (size[0] - 1) / 2.0], [0.0, f, (size[1] - 1) / 2.0], [0.0, 0.0, 1.0]])
    R, t = relative_pose(fit.F, K, K, m1, m2)
    v1 = np.c_[m1, np.ones(len(m1))] @ np.linalg.inv(K).T
    v2 = np.c_[m2, np.ones(len(m2))] @ np.linalg.inv(K).T @ R
    z = np.asarray(triangulate_rays(-R.T @ t * baseline, v1, v2))[:, 2]

    def warp(H, p):
        h = np.c_[p, np.ones(len(p))] @ H.T
        return h[:, :2] / h[:, 2:3]

    d_sparse = warp(H1, m1)[:, 0] - warp(H2, m2)[:, 0]
    front = z > 0
    if front.sum() < 8:
        raise DstereoError(f"{name}: fewer than 8 matches triangulate in front of the cameras; check the focal length")
    Q = uncalibrated_q(f, size, baseline, d_sparse[front], z[front])
    timings["rectify_s"] = time.perf_counter() - t0
    from dstereo.stereo.range_bounds import width_bounds
    from dstereo.stereo.search_range import from_sparse

    t0 = time.perf_counter()
    # The sparse matches that fitted F (warped onto the rectified rows) give the range estimate here.
    estimate = from_sparse(np.sign(Q[3, 2]) * d_sparse[front], size[0])
    disparity, params, search_range, warnings = match_in_range(
        name, left_rect, right_rect, config, Q, np.zeros(left_rect.shape[:2], bool), estimate=estimate,
        bounds=width_bounds(size[0], "homography rectification (its infinity is not known): image width"))
    timings["disparity_s"] = time.perf_counter() - t0
    if not scaled:
        warnings.insert(0, f"{name}: no baseline given: the reconstruction is UNSCALED (baseline = 1)")
    matrices = {"H1": H1, "H2": H2, "F": fit.F, "Q": Q, "R": R, "t": t}
    summary = {"mode": "uncalibrated", "units": "mm" if scaled else "unscaled (baseline = 1)", "scaled": scaled,
               "frame": "homography-rectified left image (approximately the left camera; distortion ignored)",
               "matches": int(len(matches.left)), "inliers": int(fit.inliers.sum()), "f_sampson_rms_px": fit.rms,
               "focal_px": f, "sgbm": params.as_dict(), "search_range": search_range,
               "uncertainty": {"computed": False, "note": "uncalibrated path: no calibration covariance or Q to "
                               "propagate; point uncertainties need --calib"}, "refine": {"enabled": False}}
    from dstereo.stereo.density_check import checked_density

    disparity, filled, fill_sigma, _ = checked_density(name, left, right, left_rect, right_rect, exact_maps, disparity,
                                                       params, Q, np.zeros(disparity.shape, bool), config, summary,
                                                       timings, warnings)  # refined, filled, the density check
    return points_and_summary(name, left_rect, right_rect, disparity, Q, np.eye(3), config, matrices, summary, timings,
                              warnings, filled, fill_sigma)
