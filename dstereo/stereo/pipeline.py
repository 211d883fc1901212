"""The reconstruction pipeline: rectify, match (SGBM), triangulate, and write a results folder atomically.

Calibrated path: Bouguet rectification in JAX (`dstereo.stereo.rectify`), images resampled by `cv2.remap` on maps
computed in JAX, SGBM disparity, optionally refined to sub-pixel accuracy (`dstereo.stereo.subpixel`: the originals resampled again
by cubic B-spline at the exact map positions, Lucas-Kanade along the rows; `refine`), points from Q in the
original left camera frame (mm). A Middlebury-style calibration of an already rectified pair skips the
resampling.
Uncalibrated path (thesis 4.2.2.4): SIFT matches, robust F, Hartley homographies; Q from the user's focal
length and baseline (baseline 1: unscaled), its disparity offset fitted to the sparse matches triangulated
from E = K^T F K. Library functions return results and warnings; they never print.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from dstereo.stereo.disparity import PRESETS, SGBMParams, compute_disparity, disparity_range
from dstereo.errors import DstereoError
from dstereo.io.calib_files import StereoCalibration
from dstereo.io.results import check_output

LOW_DENSITY = 0.10  # below this valid fraction the result carries a warning


@dataclass(frozen=True)
class ReconstructionConfig:
    """Everything a reconstruction can be told (the CLI and configuration files fill it).

    depth_range (mm) sets the SGBM search range; without it (and without min/num_disparities in `sgbm_user`)
    the range comes from the data (`dstereo.stereo.search_range`, `match_in_range`; `search_range` (min, num) is a range a
    program chose, widened like an estimate when saturated), as do block size and speckle window
    unless named in `sgbm_user`; alpha / zero_disparity are stereoRectify's (the default
    zero_disparity=False keeps each rectified image centred on its own view, as converging rigs need); roi
    (x, y, w, h) on the rectified left image keeps points inside it only; outlier_neighbours > 0 turns on
    statistical outlier removal; max_jump is the relative depth step that breaks the mesh. refine: SGBM's
    pixel-locked sub-pixel disparity is refined (`dstereo.stereo.subpixel`); a pixel the refinement cannot refine
    is dropped (NaN), not kept at SGBM's value. Off by default: on rendered speckle it cuts the surface error
    2.6x, but on Middlebury 2014 (slanted, occluding, real images) it drops 4-10 % of the pixels and does not
    improve the good ones (experiments/results/middlebury.md).
    """

    sgbm: SGBMParams = PRESETS["default"]
    sgbm_user: tuple[str, ...] = ()  # SGBM fields the user set (CLI/config), kept as given; "preset": all of them
    depth_range: tuple[float, float] | None = None
    search_range: tuple[int, int] | None = None  # (min, num) chosen by a caller (a sequence's first frame), not a user
    alpha: float = -1.0
    zero_disparity: bool = False
    undistort: str = "opencv"
    color_matching: bool = False
    roi: tuple[int, int, int, int] | None = None
    outlier_neighbours: int = 0
    outlier_std: float = 2.0
    max_jump: float = 0.05
    refine: bool = False
    # uncalibrated path
    focal_mm: float | None = None
    pixel_size_mm: float | None = None
    crop_factor: float | None = None
    focal_px: float | None = None
    baseline_mm: float | None = None
    ratio: float = 0.75
    f_threshold: float = 1.0
    # point uncertainty (calibrated path): disparity_sigma None = estimated from a left-right check
    uncertainty: bool = True
    disparity_sigma: float | None = None
    full_covariance: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class PairResult:
    """One reconstructed pair: rectified images (BGR), disparity (px), depth and points (mm, left camera frame)."""

    name: str
    left_rect: np.ndarray
    right_rect: np.ndarray
    disparity: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    matrices: dict[str, np.ndarray]
    summary: dict
    warnings: list[str] = field(default_factory=list)
    uncertainty: object | None = None  # point_uncertainty.PointUncertainty (calibrated path)
    exact_rect: tuple[np.ndarray, np.ndarray] | None = None  # grey float64 rectified pair the refinement used


def read_image(path: str | Path) -> np.ndarray:
    """8-bit BGR image (grey images are expanded to three channels)."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DstereoError(f"image {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise DstereoError(f"image {path} cannot be decoded; give a PNG, JPEG or TIFF file")
    return image


def check_pair(left: np.ndarray, right: np.ndarray, calib: StereoCalibration | None, names=("left", "right")):
    """Same size for both images, and the calibration's image size when it states one."""
    if left.shape[:2] != right.shape[:2]:
        raise DstereoError(
            f"{names[0]} is {left.shape[1]}x{left.shape[0]} but {names[1]} is {right.shape[1]}x{right.shape[0]}; "
            "a stereo pair must have equal sizes (crop or resize both the same way)"
        )
    size = (left.shape[1], left.shape[0])
    if calib is not None and calib.image_size is not None and tuple(calib.image_size) != size:
        raise DstereoError(
            f"calibration {calib.source} is for {calib.image_size[0]}x{calib.image_size[1]} images but "
            f"{names[0]} is {size[0]}x{size[1]}; use images of the calibrated size or recalibrate at this one"
        )


def _grey(image: np.ndarray) -> np.ndarray:
    import cv2

    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


# --- search range and matching (issue 14): sizing, range source, saturation check and widening ----------------


def user_sgbm_names(config: ReconstructionConfig) -> set[str]:
    """SGBM fields the user chose: named in `sgbm_user` (CLI, configuration file; "preset" = all) or set to a
    value other than the default's (library callers passing their own SGBMParams)."""
    from dataclasses import fields

    names = {f.name for f in fields(SGBMParams)}
    if "preset" in config.sgbm_user:
        return names
    default = PRESETS["default"]
    return set(config.sgbm_user) | {n for n in names if getattr(config.sgbm, n) != getattr(default, n)}


def sized_sgbm(params: SGBMParams, user: set[str], shape: tuple[int, ...]) -> SGBMParams:
    """SGBM settings that follow the image where the user did not set them: block size 5 up to ~1.2 Mpx, 7 up to
    ~5 Mpx, 9 beyond (a 12 Mpx camera resolves the same texture over 2-3x more pixels than a 640 x 480 webcam);
    speckle window 100 px per 640 x 480 of image area (at least 100, at most 2000), so a speck is the same share
    of the image. P1/P2 (None) follow block size and channels by the thesis rule (`SGBMParams.penalties`).
    Measured on four Middlebury scenes upscaled 2x (1.4 Mpx), bad-2.0 with missing = bad, block 5 / 7 / 9:
    Adirondack 22.1 / 17.5 / 16.0 %, Motorcycle 10.0 / 8.8 / 8.6, Piano 24.6 / 23.3 / 23.2, Teddy 6.8 / 6.8 / 7.5."""
    pixels = shape[0] * shape[1]
    changes = {}
    if "block_size" not in user:
        changes["block_size"] = 5 if pixels <= 1_200_000 else (7 if pixels <= 5_000_000 else 9)
    if "speckle_window_size" not in user:
        changes["speckle_window_size"] = int(np.clip(round(100 * pixels / (640 * 480)), 100, 2000))
    return params.with_overrides(changes)


def initial_range(config: ReconstructionConfig, user: set[str], Q: np.ndarray, left_rect, right_rect,
                  calib: StereoCalibration | None = None, estimate=None):
    """The search range before matching (`dstereo.stereo.search_range`, sources in order): the user's depth range or
    SGBM range, a Middlebury file's ndisp, the given sparse `estimate`, sparse matches on the rectified pair,
    the calibration's board depths (too few sparse matches), the default."""
    from dstereo.stereo import search_range as sr

    if config.depth_range is not None:
        b = 1.0 / abs(Q[3, 2])
        lo, num = disparity_range(Q[2, 3], b, *config.depth_range, doffs=Q[3, 3] * b, margin=2.0)
        return sr.SearchRange(lo, num, "--z-min/--z-max", f"depth {config.depth_range[0]:g}.."
                              f"{config.depth_range[1]:g} mm, margin 2 px", user=True)
    if {"min_disparity", "num_disparities"} & user:
        what = "preset" if "preset" in config.sgbm_user else "--sgbm min_disparity/num_disparities"
        return sr.SearchRange(config.sgbm.min_disparity, config.sgbm.num_disparities, what, user=True)
    if config.search_range is not None:
        return sr.SearchRange(*config.search_range, "first frame's range", "chosen on the sequence's first frame")
    if calib is not None and calib.rectified and (found := sr.from_middlebury(calib.extras)) is not None:
        return found
    if estimate is None:
        estimate = sr.from_sparse(sr.sparse_disparities(left_rect, right_rect, 1.0 if Q[3, 2] >= 0 else -1.0),
                                  left_rect.shape[1])
    if estimate is not None:
        return estimate
    if calib is not None and (found := sr.from_board_depths(calib.extras, Q, left_rect.shape[1])) is not None:
        return found
    return sr.SearchRange(*sr.DEFAULT_RANGE, "default", f"fewer than {sr.MIN_MATCHES} sparse matches on the "
                          "rectified rows to estimate the range from")


def match_in_range(name: str, left_rect, right_rect, config: ReconstructionConfig, Q: np.ndarray,
                   outside: np.ndarray, calib: StereoCalibration | None = None, estimate=None):
    """SGBM with settings sized to the image over a search range from the data, checked for saturation: a range
    the tool chose is widened on the side the scene runs off and matched again (bounded); a user's range is
    kept, with a warning. Returns (disparity, params, summary['search_range'], warnings)."""
    from dstereo.stereo import search_range as sr

    user = user_sgbm_names(config)
    base = sized_sgbm(config.sgbm, user, left_rect.shape)
    rng = initial_range(config, user, Q, left_rect, right_rect, calib, estimate)
    sign = 1.0 if Q[3, 2] >= 0 else -1.0
    tries, warnings = [], []
    if rng.source == "default":
        warnings.append(f"{name}: disparity search range {rng.min_disparity}..{rng.max_disparity} px is the default "
                        f"({rng.detail}); set --z-min/--z-max to the scene's depth range")
    while True:
        params = base.with_overrides({"min_disparity": rng.min_disparity, "num_disparities": rng.num_disparities})
        disparity = _disparity(left_rect, right_rect, params, Q, config.color_matching)
        disparity[outside] = np.nan
        sat = sr.saturation(sign * disparity, rng, ~outside)
        tries.append({"min_disparity": rng.min_disparity, "max_disparity": rng.max_disparity, **sat.as_dict()})
        if not sat.saturated or rng.user or rng.widened >= sr.MAX_WIDENINGS:
            break
        grown = sr.widened(rng, sat, left_rect.shape[1])
        if grown is None:
            break
        rng = grown
    if sat.saturated:
        warnings.append(sr.saturation_warning(name, rng, sat, Q))
    summary = rng.as_dict(Q) | {"saturation": sat.as_dict(), "tries": tries,
                                "sign": "disparities sign-normalised: sign(Q[3,2]) (u_left - u_right)"}
    if rng.user:
        summary["sparse_check"] = _sparse_check(name, rng, left_rect, right_rect, sign, Q, warnings)
    return disparity, params, summary, warnings


def _sparse_check(name: str, rng, left_rect, right_rect, sign: float, Q: np.ndarray, warnings: list) -> dict:
    """A user's range checked against sparse matches on the rectified pair (independent of SGBM, which does not
    always pile up at a range end when the scene runs past it): a warning when over 2 % of them lie outside."""
    from dstereo.stereo import search_range as sr

    d_s = sr.sparse_disparities(left_rect, right_rect, sign)
    if len(d_s) < sr.MIN_MATCHES:
        return {"matches": int(len(d_s)), "outside_share": None}
    below = float(np.mean(d_s < rng.min_disparity))
    above = float(np.mean(d_s > rng.max_disparity))
    if below + above > sr.SPARSE_OUTSIDE_SHARE:
        lo, hi = np.percentile(d_s, [0.5, 99.5])
        near, far = sr.depth_for(Q, hi), sr.depth_for(Q, lo)
        warnings.append(f"{name}: {100 * (below + above):.0f}% of {len(d_s)} sparse matches lie outside the disparity "
                        f"search range {rng.min_disparity}..{rng.max_disparity} px ({rng.source}): {100 * below:.0f}% "
                        f"below, {100 * above:.0f}% above; they put the scene at {lo:.0f}..{hi:.0f} px (depth "
                        f"{near:.0f}..{far:.0f} mm); widen the range to that, or drop the flags to let dstereo choose")
    return {"matches": int(len(d_s)), "below_share": below, "above_share": above}


def _disparity(left, right, params: SGBMParams, Q: np.ndarray, color: bool) -> np.ndarray:
    """SGBM on the rectified pair; a rig whose right camera sits on the left (Q[3,2] < 0) is matched mirrored."""
    a, b = (left, right) if color else (_grey(left), _grey(right))
    if Q[3, 2] >= 0:
        return compute_disparity(a, b, params)
    mirrored = compute_disparity(np.ascontiguousarray(a[:, ::-1]), np.ascontiguousarray(b[:, ::-1]), params)
    return -mirrored[:, ::-1]


def _require_disparity(name: str, disparity: np.ndarray, summary: dict) -> None:
    if not np.isfinite(disparity).any():
        raise DstereoError(
            f"{name}: SGBM found no valid disparity (range {summary['sgbm']['min_disparity']}.."
            f"{summary['sgbm']['min_disparity'] + summary['sgbm']['num_disparities'] - 1} px). The images may lack "
            "texture, or the range misses the scene: set --z-min/--z-max to the object's depth range or widen "
            "--sgbm num_disparities; check that --left and --right are not swapped"
        )


def _refine(name: str, left, right, maps, disparity: np.ndarray, summary: dict, timings: dict, warnings: list):
    """Refined disparity and the exact rectified grey pair (`dstereo.stereo.subpixel`); summary['refine'] says how
    many of SGBM's pixels it dropped (a warning when more than half)."""
    from dstereo.stereo.subpixel import dropped_fraction, exact_pair, refine_disparity

    _require_disparity(name, disparity, summary)
    t0 = time.perf_counter()
    exact = exact_pair(left, right, maps)
    refined = refine_disparity(*exact, disparity)
    timings["refine_s"] = time.perf_counter() - t0
    summary["refine"] = {"enabled": True, "dropped_fraction": dropped_fraction(disparity, refined),
                         "method": "cubic B-spline re-rectification + Lucas-Kanade along rows (dstereo.stereo.subpixel); "
                                   "dropped_fraction: share of SGBM's pixels the refinement could not refine (NaN)"}
    if summary["refine"]["dropped_fraction"] > 0.5:
        warnings.append(f"{name}: the sub-pixel refinement dropped {100 * summary['refine']['dropped_fraction']:.0f}% "
                        "of SGBM's pixels (little texture, or surfaces slanted or broken within a few pixels); "
                        "check disparity.png, or run with --no-refine")
    return refined, exact


def _finish(name, left_rect, right_rect, disparity, Q, R1, config: ReconstructionConfig, matrices, summary,
            timings, warnings) -> PairResult:
    """Disparity -> points in the left frame, ROI, outliers, density checks and the summary."""
    from dstereo.io.pointcloud import remove_statistical_outliers
    from dstereo.stereo.triangulate import reproject_disparity, to_original_left

    t0 = time.perf_counter()
    if not summary["refine"]["enabled"]:  # refined: checked on SGBM's map before the refinement
        _require_disparity(name, disparity, summary)
    points = np.array(to_original_left(reproject_disparity(disparity.astype(np.float64), Q), R1))  # writable
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
    timings["triangulate_s"] = time.perf_counter() - t0
    fraction = float(valid.mean())
    if fraction < LOW_DENSITY:
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
                      matrices, summary, warnings)


def reconstruct_calibrated(calib: StereoCalibration, left: np.ndarray, right: np.ndarray,
                           config: ReconstructionConfig = ReconstructionConfig(), name: str = "pair") -> PairResult:
    """Rectify (unless already rectified), SGBM, and triangulate one pair with a stereo calibration."""
    import cv2

    from dstereo.stereo.rectify import rectified_from_projections, rectify_calibration, rectify_map

    check_pair(left, right, calib)
    size = (left.shape[1], left.shape[0])
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if calib.rectified:
        rect = rectified_from_projections(*calib.projections(), size)
        left_rect, right_rect = left, right
        outside = np.zeros(left.shape[:2], bool)
        exact_maps = None
    else:
        rect = rectify_calibration(calib, size, alpha=config.alpha, zero_disparity=config.zero_disparity,
                                   undistort=config.undistort)
        if rect.vertical:
            raise DstereoError(
                f"calibration {calib.source}: the baseline is vertical; SGBM matches along rows, so rotate both "
                "images (and the calibration) by 90 degrees"
            )
        exact_maps = [tuple(np.asarray(m, np.float64) for m in rectify_map(k, d, R, P, rect.size))
                      for k, d, R, P in ((calib.k1, calib.D1, rect.R1, rect.P1), (calib.k2, calib.D2, rect.R2, rect.P2))]
        left_rect, right_rect = (cv2.remap(img, mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR,
                                           borderMode=cv2.BORDER_CONSTANT)
                                 for img, (mx, my) in zip((left, right), exact_maps))
        mx, my = exact_maps[0]
        outside = (mx < 0) | (my < 0) | (mx > size[0] - 1) | (my > size[1] - 1)
    timings["rectify_s"] = time.perf_counter() - t0
    Q = np.asarray(rect.Q)
    t0 = time.perf_counter()
    disparity, params, search_range, warnings = match_in_range(name, left_rect, right_rect, config, Q, outside,
                                                               calib=calib)
    timings["disparity_s"] = time.perf_counter() - t0
    matrices = {k: np.asarray(getattr(rect, k)) for k in ("R1", "R2", "P1", "P2", "Q", "roi1", "roi2")}
    summary = {"mode": "calibrated", "calibration": calib.source, "units": "mm", "scaled": True,
               "frame": "original left camera (x right, y down, z forward); pixel grid of the rectified left image",
               "sgbm": params.as_dict(), "search_range": search_range, "alpha": config.alpha,
               "zero_disparity": config.zero_disparity, "refine": {"enabled": False}}
    exact = None
    if config.refine:
        disparity, exact = _refine(name, left, right, exact_maps, disparity, summary, timings, warnings)
    result = _finish(name, left_rect, right_rect, disparity, Q, np.asarray(rect.R1), config, matrices, summary,
                     timings, warnings)
    result.exact_rect = exact
    if config.uncertainty:
        add_uncertainty(result, calib, config, params, originals=(left, right))
    return result


def add_uncertainty(result: PairResult, calib: StereoCalibration, config: ReconstructionConfig,
                    params: SGBMParams | None = None, originals=None) -> PairResult:
    """Fill `result.uncertainty` and summary['uncertainty'] (see `dstereo.uncertainty.points`) with the
    per-pixel disparity noise of `disparity_sigma_hook`."""
    from dstereo.uncertainty.points import point_covariances

    t0 = time.perf_counter()
    sigma_d, source = disparity_sigma_hook(result, config, params, originals)
    result.uncertainty = point_covariances(calib, result, sigma_d, full=config.full_covariance,
                                           sigma_d_source=source)
    result.summary["uncertainty"] = result.uncertainty.summary()
    result.summary.setdefault("timings_s", {})["uncertainty_s"] = time.perf_counter() - t0
    if not result.uncertainty.calibration_included:
        result.warnings.append(f"{result.name}: calibration uncertainty not included ({calib.source} has no "
                               "covariance); the point sigmas cover disparity noise only")
    return result


def disparity_sigma_hook(result: PairResult, config: ReconstructionConfig, params: SGBMParams | None = None,
                         originals=None):
    """(sigma_d (h, w) px, source) of the result's disparity: the per-pixel model of `dstereo.stereo.disparity_noise`
    (or the configured constant), its level set by the scatter on smooth parts of the map (plane check);
    the check goes to summary['disparity_noise'], its warnings to the result's."""
    from dstereo.stereo.disparity_noise import disparity_sigma_map

    refined = result.exact_rect is not None
    rectified = result.exact_rect if refined else tuple(_grey(x).astype(np.float64) for x in
                                                        (result.left_rect, result.right_rect))
    originals = originals if originals is not None else (result.left_rect, result.right_rect)
    block = (params or config.sgbm).block_size
    sigma, info, warnings = disparity_sigma_map(originals, rectified, result.disparity, refined, block,
                                                config.disparity_sigma, result.name)
    result.summary["disparity_noise"] = info
    result.warnings.extend(warnings)
    return sigma, info["basis"] + (f"; scaled by {info['scaled_by']:.3g} by the plane check"
                                   if info["scaled_by"] != 1.0 else "")


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
    from dstereo.stereo.search_range import from_sparse

    t0 = time.perf_counter()
    # The sparse matches that fitted F (warped onto the rectified rows) give the range estimate here.
    estimate = from_sparse(np.sign(Q[3, 2]) * d_sparse[front], size[0])
    disparity, params, search_range, warnings = match_in_range(
        name, left_rect, right_rect, config, Q, np.zeros(left_rect.shape[:2], bool), estimate=estimate)
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
    if config.refine:
        disparity, _ = _refine(name, left, right, exact_maps, disparity, summary, timings, warnings)
    return _finish(name, left_rect, right_rect, disparity, Q, np.eye(3), config, matrices, summary, timings,
                   warnings)


def run_reconstruction(
    pairs: list[tuple[str | Path, str | Path]],
    out: str | Path,
    calib_path: str | Path | None = None,
    config: ReconstructionConfig = ReconstructionConfig(),
    force: bool = False,
) -> list[PairResult]:
    """Reconstruct every (left, right) pair and write the results folder (one sub-folder per pair if several)."""
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.reconstruction_files import json_default, write_atomically, write_pair

    check_output(out, force)
    if not pairs:
        raise DstereoError("no image pair given; pass --left and --right")
    calib = read_stereo_calibration(calib_path) if calib_path is not None else None
    results = []
    for left_path, right_path in pairs:
        left, right = read_image(left_path), read_image(right_path)
        check_pair(left, right, calib, names=(str(left_path), str(right_path)))
        name = Path(left_path).stem
        if calib is None:
            results.append(reconstruct_uncalibrated(left, right, config, name))
        else:
            results.append(reconstruct_calibrated(calib, left, right, config, name))
    names = [r.name for r in results]
    if len(set(names)) != len(names):
        for i, r in enumerate(results):
            r.name = f"{i:02d}_{r.name}"

    def fill(tmp: Path):
        if len(results) == 1:
            write_pair(tmp, results[0], config)
            return
        for r in results:
            (tmp / r.name).mkdir()
            write_pair(tmp / r.name, r, config)
        index = {"pairs": [r.summary for r in results], "config": config.as_dict()}
        (tmp / "summary.json").write_text(json.dumps(index, indent=2, default=json_default))

    write_atomically(out, force, fill)
    return results


# The configuration files' loader lives in dstereo.config.reconstruction (one configuration system for every
# command); these names stay importable from here.
from dstereo.config.reconstruction import CONFIG_NAMES, config_from_mapping, load_config  # noqa: E402,F401
