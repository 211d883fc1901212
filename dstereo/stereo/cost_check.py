"""The grey-level cost's map checked by the rank cost's (issue 30): for views lit alike, `--cost auto` matches the
grey levels (the more precise cost where the views agree photometrically) and runs SGBM a second time on the
views' rank transforms over the same range. Where, around a pixel, the pixels both costs matched mostly disagree
(more than AGREEMENT_PX apart on at least MAJORITY of them, and at least MIN_VOTES of them, within a REGION_PX x
REGION_PX window), the grey levels' map has drifted there and every grey-level match in it is dropped.

Why: SGBM on the grey levels matches weak texture the rank cost leaves alone (Middlebury's Adirondack, as it is:
94 % dense against 79 %, mostly right), but on a blank wall whose brightness ramps across it a small photometric
difference between the views moves its match by pixels, and SGBM's smoothness carries the wrong disparity over
the wall (Piano, as it is: p90 depth error 5.1 %). The rank transform sees a gain, an offset or a gamma as no
change; it matches few of the wall's pixels, and those disagree with the grey levels. A single disagreeing pixel
says little (at such pixels each cost is right about half the time, measured on the five shared Middlebury scenes:
0.39-0.49 for the grey levels, 0.43-0.52 for the ranks; on renders' depth edges the grey levels more often), so
isolated disagreements are kept, and a region is dropped only when the rank cost's matches there mostly disagree.
Measured (experiments/results/middlebury_lighting.md): Piano as it is p90 5.11 -> 2.75 %, density 89.7 -> 84.6 %
(4.4 % of the pixels dropped); the other four scenes 0.0-0.5 %, density 0.0-0.5 points lower, p90 the same or
lower; on renders (the four outdoor scenes of `synth.outdoor`, a speckled sphere) no pixel. The window is not a
fine setting: at 15 px Piano reads p90 3.09 %, density 84.6 %, the others lose up to 1.7 points, the renders
nothing; dropping every disagreeing pixel instead (no vote) reads Piano 3.96 % and costs the renders 0.1-0.4 points
of pixels within 1 px."""

from __future__ import annotations

import numpy as np

AGREEMENT_PX = 1.0  # the left-right check's tolerance (`range_tries.LR_TOLERANCE_PX`): SGBM's own disp12MaxDiff
REGION_PX = 31  # the window a region's vote is taken over: SGBM's smoothness carries a match tens of px
MAJORITY = 0.5  # a region is dropped when at least this share of its pixels both costs matched disagree
MIN_VOTES = 3  # and at least this many pixels were matched by both (fewer: the rank cost says nothing there)


def _window_counts(mask: np.ndarray) -> np.ndarray:
    """How many pixels of `mask` lie in each pixel's REGION_PX x REGION_PX window (outside the image: none)."""
    from scipy.ndimage import uniform_filter

    mean = uniform_filter(mask.astype(np.float64), REGION_PX, mode="constant", cval=0.0)
    return np.rint(mean * REGION_PX ** 2)


def cross_checked(disparity: np.ndarray, other: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, dict]:
    """(`disparity` with NaN over the regions where `other` (the rank cost's map over the same range, same
    convention) mostly disagrees, the figures for summary.json). `usable`: the pixels that count (the shares are
    of them)."""
    both = np.isfinite(disparity) & np.isfinite(other)
    conflict = both & (np.abs(disparity - other) > AGREEMENT_PX)
    votes, against = _window_counts(both), _window_counts(conflict)
    drifted = (votes >= MIN_VOTES) & (against >= MAJORITY * votes)
    dropped = np.isfinite(disparity) & drifted
    n = max(int(usable.sum()), 1)
    share = lambda m: int((m & usable).sum()) / n  # noqa: E731
    figures = {"agreement_px": AGREEMENT_PX, "region_px": REGION_PX, "majority": MAJORITY, "min_votes": MIN_VOTES,
               "matched_share": share(np.isfinite(disparity)), "rank_matched_share": share(np.isfinite(other)),
               "both_share": share(both), "disagree_share": share(conflict), "dropped_share": share(dropped),
               "kept_share": share(np.isfinite(disparity) & ~drifted),
               "shares": "of the pixels with a source in both images"}
    return np.where(drifted, np.float32(np.nan), disparity).astype(disparity.dtype), figures
