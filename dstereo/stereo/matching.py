"""Matching a rectified pair (issue 14): SGBM sized to the images, the search range from the data or the user,
the saturation check and widening, and the optional sub-pixel refinement."""

from __future__ import annotations

import time

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.stereo.disparity import PRESETS, SGBMParams, compute_disparity, disparity_range
from dstereo.stereo.pair_result import grey
from dstereo.config.reconstruction_config import ReconstructionConfig, user_sgbm_names  # noqa: F401


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
                   outside: np.ndarray, calib: StereoCalibration | None = None, estimate=None, bounds=None):
    """SGBM with settings sized to the image over a search range from the data, checked for saturation: a range
    the tool chose is cut to the rig's disparity `bounds` (default: `range_bounds.geometric_bounds` of Q, the width
    and the calibration's boards) and widened on the side the scene runs off while a widening keeps the valid
    and left-right consistent shares (`dstereo.stereo.range_tries`); a user's range is kept, with a warning.
    Returns (disparity, params, summary['search_range'], warnings)."""
    from dstereo.stereo import search_range as sr
    from dstereo.stereo.range_bounds import geometric_bounds
    from dstereo.stereo.range_tries import Matcher, refusal_note, search

    user = user_sgbm_names(config)
    rng = initial_range(config, user, Q, left_rect, right_rect, calib, estimate)
    if bounds is None:
        bounds = geometric_bounds(Q, left_rect.shape[1], calib.extras if calib is not None else None)
    if not rng.user:
        rng = sr.within(rng, bounds)
    cost = chosen_cost(left_rect, right_rect, config)
    a, b = matched_images(left_rect, right_rect, config, cost["cost"])  # transformed once for every try
    matcher = Matcher(lambda p: sgbm_disparity(a, b, p, Q, True),
                      lambda p: sgbm_right_disparity(a, b, p, Q, True),
                      ~outside, 1.0 if Q[3, 2] >= 0 else -1.0, bounds, sized_sgbm(config.sgbm, user, left_rect.shape))
    warnings = []
    if rng.source == "default":
        warnings.append(f"{name}: disparity search range {rng.min_disparity}..{rng.max_disparity} px is the default "
                        f"({rng.detail}); set --z-min/--z-max to the scene's depth range")
    kept = search(matcher, rng)
    disparity = kept.disparity
    if cost.get("checked_by") == "rank":  # views lit alike: the grey levels' map checked by the rank cost's
        from dstereo.stereo.cost_check import cross_checked
        from dstereo.stereo.rank_transform import rank_transform

        ra, rb = rank_transform(grey(left_rect)), rank_transform(grey(right_rect))
        other = sgbm_disparity(ra, rb, kept.params, Q, True)
        other[outside] = np.nan
        disparity, cost["cross_check"] = cross_checked(disparity, other, ~outside, kept.params.speckle_window_size)
    if kept.sat.saturated:
        warnings.append(sr.saturation_warning(name, kept.rng, kept.sat, Q) + refusal_note(matcher, kept))
    summary = kept.rng.as_dict(Q) | {
        "saturation": kept.sat.as_dict(), "valid_share": kept.valid_share, "lr_consistent_share": kept.lr_share,
        "tries": [t.as_dict() for t in matcher.tries], "bounds": bounds.as_dict(), "matching_cost": cost,
        "sign": "disparities sign-normalised: sign(Q[3,2]) (u_left - u_right)",
        "shares": "of the pixels with a source in both images: valid = SGBM found a disparity; left-right "
                  "consistent = the right image's map agrees within 1 px (measured only when a widening is tried)"}
    if kept.rng.user:
        summary["sparse_check"] = _sparse_check(name, kept.rng, left_rect, right_rect, matcher.sign, Q, warnings)
    return disparity, kept.params, summary, warnings


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


MATCHING_COSTS = ("auto", "rank", "intensity")

# 'auto' takes the rank cost when the two views' brightness or contrast differ by more than this: the larger of
# |log| of the ratio of their median grey levels and of their 10-90 % spreads (0.25: a change by 28 %). Views
# lit alike differ only by what each sees: measured 0.008-0.071 on the shared Middlebury scenes and 0.02-0.15 on
# the real rigs (rig640's cameras differ in exposure by 15 %); the issue's relighting (gain 0.7, gamma 1.3) gives
# 0.38-0.87. The rank cost survives any such change but costs precision where there is none (a rendered cork
# sample's surface RMS 0.054 -> 0.071 mm, a speckled sphere's share within 1 % 0.94 -> 0.90).
LIGHTING_MISMATCH = 0.25


def lighting_mismatch(left, right) -> float:
    """The brightness-or-contrast gap of the module's LIGHTING_MISMATCH between two views (0: lit alike)."""
    a, b = (np.percentile(grey(x).astype(float), [10.0, 50.0, 90.0]) for x in (left, right))
    level = abs(np.log(max(b[1], 1.0) / max(a[1], 1.0)))
    spread = abs(np.log(max(b[2] - b[0], 1.0) / max(a[2] - a[0], 1.0)))
    return float(max(level, spread))


def chosen_cost(left, right, config: ReconstructionConfig) -> dict:
    """{'cost': 'rank' | 'intensity', 'why': ...} for `matching_cost` ('auto': by `lighting_mismatch`; where it
    takes the grey levels, also 'checked_by': 'rank': `match_in_range` drops the regions where SGBM on the rank
    transforms mostly disagrees, `dstereo.stereo.cost_check`)."""
    if config.matching_cost not in MATCHING_COSTS:
        raise DstereoError(f"`matching_cost` {config.matching_cost!r}: use one of {list(MATCHING_COSTS)}")
    if config.matching_cost != "auto":
        return {"cost": config.matching_cost, "why": "given"}
    gap = lighting_mismatch(left, right)
    if gap > LIGHTING_MISMATCH:
        return {"cost": "rank", "lighting_mismatch": gap, "why": (
            f"the views' brightness or contrast differ (|log ratio| {gap:.3f} > {LIGHTING_MISMATCH:g}: lit or "
            "exposed differently): SGBM on their rank transforms")}
    return {"cost": "intensity", "checked_by": "rank", "lighting_mismatch": gap, "why": (
        f"the views' brightness and contrast agree (|log ratio| {gap:.3f} <= {LIGHTING_MISMATCH:g}): SGBM on the "
        "grey levels, the more precise cost for views lit alike, checked by SGBM on the rank transforms (regions "
        "where the two mostly disagree dropped: dstereo.stereo.cost_check)")}


def matched_images(left, right, config: ReconstructionConfig, cost: str | None = None):
    """The pair SGBM matches with `cost` (default: `chosen_cost`'s): 'rank': the rank transform of each grey image
    (`dstereo.stereo.rank_transform`: survives a brightness or contrast change between the views); 'intensity':
    the grey images, or the colour ones with `color_matching` (the matching before issue 30)."""
    cost = cost or chosen_cost(left, right, config)["cost"]
    if cost == "rank":
        from dstereo.stereo.rank_transform import rank_transform

        return rank_transform(grey(left)), rank_transform(grey(right))
    return (left, right) if config.color_matching else (grey(left), grey(right))


def sgbm_disparity(left, right, params: SGBMParams, Q: np.ndarray, color: bool) -> np.ndarray:
    """SGBM on the rectified pair; a rig whose right camera sits on the left (Q[3,2] < 0) is matched mirrored."""
    a, b = (left, right) if color else (grey(left), grey(right))
    if Q[3, 2] >= 0:
        return compute_disparity(a, b, params)
    mirrored = compute_disparity(np.ascontiguousarray(a[:, ::-1]), np.ascontiguousarray(b[:, ::-1]), params)
    return -mirrored[:, ::-1]


def sgbm_right_disparity(left, right, params: SGBMParams, Q: np.ndarray, color: bool) -> np.ndarray:
    """The right image's map of `sgbm_disparity` in the same raw disparities (u_left - u_right, at u_right), for
    the left-right check: SGBM on the swapped pair, mirrored where the left pair was not."""
    a, b = (left, right) if color else (grey(left), grey(right))
    if Q[3, 2] >= 0:
        return compute_disparity(np.ascontiguousarray(b[:, ::-1]), np.ascontiguousarray(a[:, ::-1]), params)[:, ::-1]
    return -compute_disparity(b, a, params)


def require_disparity(name: str, disparity: np.ndarray, summary: dict) -> None:
    if not np.isfinite(disparity).any():
        raise DstereoError(
            f"{name}: SGBM found no valid disparity (range {summary['sgbm']['min_disparity']}.."
            f"{summary['sgbm']['min_disparity'] + summary['sgbm']['num_disparities'] - 1} px). The images may lack "
            "texture, or the range misses the scene: set --z-min/--z-max to the object's depth range or widen "
            "--sgbm num_disparities; check that --left and --right are not swapped"
        )


def refine_subpixel(name: str, left, right, maps, disparity: np.ndarray, summary: dict, timings: dict, warnings: list):
    """Refined disparity and the exact rectified grey pair (`dstereo.stereo.subpixel`); summary['refine'] says how
    many of SGBM's pixels it dropped (a warning when more than half)."""
    from dstereo.stereo.subpixel import dropped_fraction, exact_pair, refine_disparity

    require_disparity(name, disparity, summary)
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

