"""The grey-level cost's map checked by the rank cost's (issue 30): for views lit alike, `--cost auto` matches the
grey levels (the more precise cost where the views agree photometrically) and runs SGBM a second time on the
views' rank transforms over the same range. Where, around a pixel, the pixels both costs matched mostly disagree
(more than AGREEMENT_PX apart on at least MAJORITY of them, and at least `min_votes` of them, within a window
REGION_SHARE of the image width across), the grey levels' map has drifted there and every grey-level match in it
is dropped.

Why: SGBM on the grey levels matches weak texture the rank cost leaves alone (Middlebury's Adirondack, as it is:
94 % dense against 79 %, mostly right), but on a blank wall whose brightness ramps across it a small photometric
difference between the views moves its match by pixels, and SGBM's smoothness carries the wrong disparity over
the wall (Piano, as it is: p90 depth error 5.1 %). The rank transform sees a gain, an offset or a gamma as no
change; it matches few of the wall's pixels, and those disagree with the grey levels. A single disagreeing pixel
says little (at such pixels each cost is right about half the time, measured on the five shared Middlebury scenes:
0.39-0.49 for the grey levels, 0.43-0.52 for the ranks), so isolated disagreements are kept. Nor does a small
blank patch inside a textured surface: SGBM carries its rims' disparity across it, right where the patch is part
of that surface (a chessboard's squares), while the rank cost's few matches inside it are noise and disagree. So
the vote is taken over a window several times such patches, a seventh of the image width (rig640, 640 px: 91 px;
Middlebury quarter size: 101-107 px), and a region votes only with at least a speckle window's worth of pixels
matched by both (`min_votes`: SGBM's speckle filter keeps no smaller blob, so fewer are one stray blob).

Measured: Piano as it is p90 5.11 -> 3.00 %, density 89.7 -> 86.4 %; the other four Middlebury scenes, the four
outdoor renders of `synth.outdoor` and a speckled sphere: nothing dropped on the pixels with a truth. On the real
rigs' boards (planes: a robust plane fit to the matching before as the truth; default_matching_real.md, last run):
rig640, 205 board pixels dropped on 1 of 25 pairs, 93 % of them within 1 px of the plane; opencv_stereo, on the 5
pairs whose plane holds at least half of the kept pixels, 10888 dropped, 64 % within 1 px: on boards the check
mostly costs right matches (density, not accuracy). The window matters: at a fixed 31 px Piano reads 2.75 % but 79 % of the board pixels dropped
were on the plane (the squares' insides); at 61 / 121 px, Piano 2.50 / 3.38 %, the board 64 / 11 %.
(experiments/results/middlebury_lighting.md, default_matching_real.md.)"""

from __future__ import annotations

import numpy as np

AGREEMENT_PX = 1.0  # the left-right check's tolerance (`range_tries.LR_TOLERANCE_PX`): SGBM's own disp12MaxDiff
REGION_SHARE = 1.0 / 7.0  # the vote's window across, as a share of the image width (the docstring: why)
MAJORITY = 0.5  # a region is dropped when at least this share of its pixels both costs matched disagree


def region_px(width: int) -> int:
    """The vote's window across (px, odd) for an image `width` px wide."""
    size = max(int(round(REGION_SHARE * width)), 3)
    return size + (size % 2 == 0)


def _window_counts(mask: np.ndarray, size: int) -> np.ndarray:
    """How many pixels of `mask` lie in each pixel's size x size window (outside the image: none)."""
    from scipy.ndimage import uniform_filter

    mean = uniform_filter(mask.astype(np.float64), size, mode="constant", cval=0.0)
    return np.rint(mean * size ** 2)


def cross_checked(disparity: np.ndarray, other: np.ndarray, usable: np.ndarray, min_votes: int
                  ) -> tuple[np.ndarray, dict]:
    """(`disparity` with NaN over the regions where `other` (the rank cost's map over the same range, same
    convention) mostly disagrees, the figures for summary.json). `usable`: the pixels that count (the shares are
    of them); `min_votes`: the fewest pixels matched by both for a window to vote (SGBM's speckle window)."""
    size = region_px(disparity.shape[1])
    both = np.isfinite(disparity) & np.isfinite(other)
    conflict = both & (np.abs(disparity - other) > AGREEMENT_PX)
    votes, against = _window_counts(both, size), _window_counts(conflict, size)
    drifted = (votes >= max(min_votes, 1)) & (against >= MAJORITY * votes)
    dropped = np.isfinite(disparity) & drifted
    n = max(int(usable.sum()), 1)
    share = lambda m: int((m & usable).sum()) / n  # noqa: E731
    figures = {"agreement_px": AGREEMENT_PX, "region_px": size, "majority": MAJORITY, "min_votes": int(min_votes),
               "matched_share": share(np.isfinite(disparity)), "rank_matched_share": share(np.isfinite(other)),
               "both_share": share(both), "disagree_share": share(conflict), "dropped_share": share(dropped),
               "kept_share": share(np.isfinite(disparity) & ~drifted),
               "shares": "of the pixels with a source in both images"}
    return np.where(drifted, np.float32(np.nan), disparity).astype(disparity.dtype), figures
