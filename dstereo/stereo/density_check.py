"""The default's density check (issue 30): `--cost auto` matches views lit alike on their grey levels and leaves
that map unfilled (`stereo.fill.fill_wanted`: its holes border its own false matches), so where the grey levels
match too little of the scene the default would end sparse. When that map's density (its matched share of the
pixels with a source in both images, after the rank check of `stereo.cost_check` and the sub-pixel refinement)
is below DENSE_ENOUGH, the default also matches the rank transforms over the same range and fills that map
(`stereo.fill`, whose sigma holds on the rank cost's maps), and keeps that try only when it is denser and its
fills pass a check that needs no truth: where the grey levels matched a pixel the rank map left to the fill, the
two estimates differ by both errors, so the robust std of their difference over sqrt(fill sigma^2 + matched
sigma^2) (RMS) reads about 1 for honest sigmas (independent errors; tests/stereo/test_density_check.py).
Every try's figures and the reason go to summary['density_check'] (the console, report.md and a warning say
it); `--cost` or `--fill` / `--no-fill` given turn the check off (what was asked is done).

Where a match can bind: both densities are measured over the pixels whose SGBM block (the window the grey
levels' cost compares) holds two grey levels or more (`varied`); a block of one level (a clipped or featureless
background, a render's sky) gives neither cost anything to bind to. Measured over the whole view, `dstereo demo`'s
scene (the speckled cork sample, 39 % of the view, on a background of one level) read 41.1 % dense and the rank try
45.8 %, "denser" only by matches fattened off the sample's rim and fills on the background (3.3 % of the view, 0.6 %
of them on blocks that are not blank; 47 shared with the grey levels' matches, too few for the fill check, so it
was kept): the demo's bounds failed (85.6 % of the points on the sample, >= 90 % asked; the refinement dropping
2.05 %, < 1 % asked). Over the blocks that are not blank the grey levels' map is 99.0 % dense: no try. Rules
measured on the same cases and not taken: a noise-relative texture mask (block std above k times the image noise,
`stereo.disparity_noise.image_noise`) also leaves out the weak texture the rank cost does match (Adirondack at
contrast x0.25 reads 78.2 / 89.9 / 91.5 % dense over it at k = 1.5 / 2 / 3, so from k = 2 the one row where the
check turns a miss into a pass is not tried); the rank try's matched (unfilled) share beating the grey levels'
does not separate the demo (42.6 against 41.1 %). With the blank-block rule every decision on
experiments/results/density_check*.md's Middlebury and real rows is the one the whole-view rule made; the
contrast-weakened outdoor renders (blank sky: 80.3-87.4 % dense) are no longer tried (before: 3 tries declined, 1
kept that raised the median depth error 1.84 -> 3.01 %). A rank try with fills that cannot be checked (fewer than
FILL_CHECK_MIN_PIXELS of them where the grey levels matched) is declined with a warning: a check that cannot be
made is not passed.

FILL_CHECK_MAX, why 1.0 and not the issue's 1.5 (set with the density over the whole view; the ratio of each try
does not depend on that): the check sees only the fills where the grey levels did match,
the fill's easier pixels (more texture); over all filled pixels the error against the truth is larger. Measured
on Middlebury with the texture weakened (contrast x0.25, blur 2 px) and contrast-weakened outdoor renders, the
nine rank tries' truth observed / predicted over the check's ratio: 0.72-1.89 (the check's 0.83 / 0.90 / 1.06 /
1.14 read 0.84 / 1.04 / 1.34 / 1.59 against the truth; 1.33-2.26 read 1.62-2.92). At 1.5 the check kept a blur
whose fills read 1.59; a ratio of at most 1.0 kept only fills within 0.67..1.5. The threshold was set on those
cases. Held out from it (experiments/results/density_check_held_out.md: contrast x0.4 with blur 1 px, 3 DN noise,
two more renders): kept 2 (truth 1.06, and 1.51 on a render's 2.1 % filled), declined 4 (truth 1.63-2.25 on
three; 1.32 on Adirondack, a dense map lost). The cost of the margin: an honest fill that reads 1.0-1.5 is
declined (Pipes at contrast x0.25: 1.06, truth 1.34; its grey levels' map already met the 80 % line on the scored
pixels)."""

from __future__ import annotations

import time

import numpy as np

DENSE_ENOUGH = 0.80  # the density line (Middlebury: density >= 80 %)
FILL_CHECK_MAX = 1.0  # the check's ratio above which the fills are not kept (the module: why not 1.5)
FILL_CHECK_MIN_PIXELS = 100  # fewer pixels estimated by both: the check is not made (too few for a robust spread)
MAD_TO_STD = 1.4826


def applies(config, summary: dict) -> bool:
    """True where the default chose the grey levels and its fill rule (`--cost auto`, no --fill / --no-fill)."""
    cost = (summary.get("search_range") or {}).get("matching_cost") or {}
    return config.matching_cost == "auto" and config.fill is None and cost.get("cost") == "intensity"


def _robust_std(x: np.ndarray) -> float:
    return float(MAD_TO_STD * np.median(np.abs(x - np.median(x))))


def varied(grey_image: np.ndarray, block: int) -> np.ndarray:
    """True where the block x block window around the pixel (SGBM's block, the window the grey levels' cost
    compares) holds two grey levels or more. A window of one level (a clipped or featureless background, a
    render's sky) gives neither cost anything to bind to: the density is measured without those pixels, so that
    a map is not called sparse for leaving them empty, nor a try denser for filling them (the module)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    g = np.asarray(grey_image)
    return maximum_filter(g, size=block, mode="nearest") > minimum_filter(g, size=block, mode="nearest")


def fill_check(disparity, filled, fill_sigma, matched, matched_sigma) -> dict:
    """The rank try's fills against the grey levels' matches at the same pixels (see the module): pixels, robust
    spread of the difference (px), the RMS predicted spread (px), their ratio (None: fewer than
    FILL_CHECK_MIN_PIXELS pixels)."""
    both = filled & np.isfinite(matched) & np.isfinite(matched_sigma)
    out = {"pixels": int(both.sum()), "max_ratio": FILL_CHECK_MAX, "ratio": None}
    if out["pixels"] < FILL_CHECK_MIN_PIXELS:
        return out
    diff = (disparity - matched)[both].astype(np.float64)
    predicted = float(np.sqrt(np.mean(fill_sigma[both] ** 2 + matched_sigma[both] ** 2)))
    observed = _robust_std(diff)
    return out | {"observed_px": observed, "predicted_px": predicted, "ratio": observed / max(predicted, 1e-12)}


def checked_density(name, left, right, left_rect, right_rect, maps, disparity, params, Q, outside, config,
                    summary: dict, timings: dict, warnings: list):
    """(disparity, filled, fill sigma, exact pair) of the pair matched as `match_in_range` left it: refined where
    `config.refine`, filled by `stereo.fill.fill_unmatched`'s rule, and, where the density check `applies` and the
    map is sparse, the rank try (the module) kept or not, summary['density_check'] saying which and why. `maps`:
    the exact rectifying maps the refinement resamples with (`refine_subpixel`)."""
    from dstereo.stereo.fill import fill_unmatched, matched_noise
    from dstereo.stereo.matching import refine_subpixel, sgbm_disparity
    from dstereo.stereo.pair_result import grey
    from dstereo.stereo.rank_transform import rank_transform

    exact = None
    if config.refine:
        disparity, exact = refine_subpixel(name, left, right, maps, disparity, summary, timings, warnings)
    disparity, filled, sigma = fill_unmatched(name, left_rect, right_rect, disparity, outside, config, summary,
                                              timings, exact)
    if not applies(config, summary):
        return disparity, filled, sigma, exact
    usable = ~outside
    scene = usable & varied(grey(left_rect), summary["sgbm"]["block_size"])  # where a match can bind
    n = max(int(scene.sum()), 1)
    density = int((np.isfinite(disparity) & scene).sum()) / n
    first = {"cost": "intensity", "fill": False, "density": density}
    record = {"threshold": DENSE_ENOUGH, "tries": [first],
              "density": "estimated share (matched or filled) of the pixels with a source in both images whose "
                         "SGBM block is not blank (two grey levels or more: where a match can bind)",
              "not_blank_share": int(scene.sum()) / max(int(usable.sum()), 1)}
    if not scene.any():
        summary["density_check"] = record | {"kept": "intensity", "why": (
            "every SGBM block of the left view is blank (one grey level): nothing to match, kept, unfilled")}
        return disparity, filled, sigma, exact
    if density >= DENSE_ENOUGH:
        summary["density_check"] = record | {"kept": "intensity", "why": (
            f"the grey levels' map is {100 * density:.1f}% dense >= {100 * DENSE_ENOUGH:.0f}% over the "
            f"{100 * record['not_blank_share']:.1f}% of the view whose blocks are not blank: kept, unfilled")}
        return disparity, filled, sigma, exact

    t0 = time.perf_counter()
    other = sgbm_disparity(rank_transform(grey(left_rect)), rank_transform(grey(right_rect)), params, Q, True)
    other[outside] = np.nan
    scratch = {"sgbm": summary["sgbm"], "refine": {"enabled": False},
               "search_range": {"matching_cost": {"cost": "rank"}}}
    scratch_timings, scratch_warnings, exact_r = {}, [], None
    if config.refine and np.isfinite(other).any():
        other, exact_r = refine_subpixel(name, left, right, maps, other, scratch, scratch_timings, scratch_warnings)
    d_r, filled_r, sigma_r = fill_unmatched(name, left_rect, right_rect, other, outside, config, scratch,
                                            scratch_timings, exact_r)
    d_r = np.where(usable, d_r, np.nan)
    density_r = int((np.isfinite(d_r) & scene).sum()) / n
    fills = (filled_r if filled_r is not None else np.zeros(d_r.shape, bool)) & usable
    filled_share = int((fills & scene).sum()) / n
    second = {"cost": "rank", "fill": True, "density": density_r, "matched_share": density_r - filled_share,
              "filled_share": filled_share, "fill_sigma_px": (scratch.get("fill") or {}).get("sigma_px")}
    record["tries"].append(second)
    check = {"pixels": 0, "max_ratio": FILL_CHECK_MAX, "ratio": None}  # made only where the try is denser
    if density_r > density and fills.any() and np.isfinite(disparity).any():
        sigma_q = matched_noise(left_rect, right_rect, disparity, summary["sgbm"]["block_size"], exact)[0]
        check = fill_check(d_r, filled_r, sigma_r, disparity, sigma_q)
    second["fill_check"] = check
    timings["density_check_s"] = time.perf_counter() - t0
    figures = (f"grey levels {100 * density:.1f}% dense (< {100 * DENSE_ENOUGH:.0f}%) over the "
               f"{100 * record['not_blank_share']:.1f}% of the view whose blocks are not blank; rank cost with the "
               f"fill {100 * density_r:.1f}% ({100 * filled_share:.1f}% filled)")
    if check["ratio"] is not None:
        figures += (f"; its fills against the grey levels' matches at {check['pixels']} pixels: spread "
                    f"{check['observed_px']:.3g} px = {check['ratio']:.2f}x predicted")
    if density_r <= density:  # said in the summary and the console; no better map to offer, so no warning
        summary["density_check"] = record | {"kept": "intensity", "why": (
            f"{figures}: the rank try is not denser, the grey levels' map kept")}
        return disparity, filled, sigma, exact
    if fills.any() and check["ratio"] is None:
        why = (f"{figures}; only {check['pixels']} of its {int(fills.sum())} filled pixels have a grey-level match "
               f"(< {FILL_CHECK_MIN_PIXELS}): its fills cannot be checked, the grey levels' map kept (--cost rank "
               "--fill forces the denser one)")
        summary["density_check"] = record | {"kept": "intensity", "why": why}
        warnings.append(f"{name}: sparse map: {why}")
        return disparity, filled, sigma, exact
    if check["ratio"] is not None and check["ratio"] > FILL_CHECK_MAX:
        why = (f"{figures} > {FILL_CHECK_MAX:g}: its fills' sigma may not hold, the grey levels' map kept "
               "(--cost rank --fill forces the denser one)")
        summary["density_check"] = record | {"kept": "intensity", "why": why}
        warnings.append(f"{name}: sparse map: {why}")
        return disparity, filled, sigma, exact
    why = f"{figures}: the denser rank try kept"
    summary["density_check"] = record | {"kept": "rank", "why": why}
    warnings.append(f"{name}: the default adapted to a sparse map: {why}")
    cost = summary["search_range"]["matching_cost"]
    summary["search_range"]["matching_cost"] = {
        "cost": "rank", "lighting_mismatch": cost.get("lighting_mismatch"), "first": cost,
        "why": "the grey levels' map too sparse (density check: summary density_check): SGBM on the rank "
               "transforms, filled"}
    summary["fill"] = scratch["fill"] | {"why": "auto: the density check kept the rank cost's filled map"}
    if config.refine:
        summary["refine"] = scratch["refine"]
    warnings.extend(scratch_warnings)
    for k, v in scratch_timings.items():
        timings[f"density_check_{k}"] = v
    return d_r, filled_r, sigma_r, exact_r
