"""Matching over a search range and widening it (issue 30): each try is measured (valid share, left-right
consistent share, saturation), a widening stays inside the rig's disparity bounds (`dstereo.stereo.range_bounds`),
and a widening try that lowers the valid share or the left-right consistent share against the range kept so far is
not kept: the range kept is the widest one that explained no less of the scene than every narrower one kept.

Why both figures: a wider range gives SGBM more candidates, so it may match pixels the narrow one left invalid
(the scene did run off) or spread false matches over disparities no scene point has (it did not: a far
background piled at the low end, or textureless sky). The valid share alone rises with false matches too; the
left-right consistent share (the right image's own map agrees within LR_TOLERANCE_PX) does not, since a false
match on one side seldom has the same false partner on the other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from dstereo.stereo.disparity import SGBMParams, left_right_check
from dstereo.stereo.range_bounds import DisparityBounds
from dstereo.stereo.search_range import MAX_WIDENINGS, Saturation, SearchRange, saturation, widened

LR_TOLERANCE_PX = 1.0  # SGBM's disparities are quantised to 1/16 px and its own disp12MaxDiff default is 1 px


@dataclass
class RangeTry:
    """One SGBM run over `rng`: its disparity (raw, NaN = invalid), the shares of the usable pixels that are valid
    and left-right consistent (None: not measured, no widening was tried), saturation, and the verdict."""

    rng: SearchRange
    params: SGBMParams
    disparity: np.ndarray
    sat: Saturation
    valid_share: float
    lr_share: float | None = None
    verdict: str = ""

    def as_dict(self) -> dict:
        return {"min_disparity": self.rng.min_disparity, "max_disparity": self.rng.max_disparity,
                "valid_share": self.valid_share, "lr_consistent_share": self.lr_share, "verdict": self.verdict,
                **self.sat.as_dict()}

    def figures(self) -> str:
        lr = "" if self.lr_share is None else f", {100 * self.lr_share:.1f}% left-right consistent"
        return f"{self.rng.min_disparity}..{self.rng.max_disparity} px: {100 * self.valid_share:.1f}% valid{lr}"


@dataclass
class Matcher:
    """What a try needs: SGBM on the pair for given params (`left`: the left image's map; `right`: the right
    image's map in the same raw disparities, for the consistency check), the pixels that count, the sign that
    normalises disparities, the rig's bounds, and the SGBM settings a range is put into."""

    left: Callable[[SGBMParams], np.ndarray]
    right: Callable[[SGBMParams], np.ndarray]
    usable: np.ndarray
    sign: float
    bounds: DisparityBounds
    base: SGBMParams
    tries: list = field(default_factory=list)

    def run(self, rng: SearchRange) -> RangeTry:
        params = self.base.with_overrides({"min_disparity": rng.min_disparity, "num_disparities": rng.num_disparities})
        disparity = self.left(params)
        disparity[~self.usable] = np.nan
        sat = saturation(self.sign * disparity, rng, self.usable, self.bounds)
        valid = float(np.isfinite(disparity[self.usable]).mean()) if self.usable.any() else 0.0
        found = RangeTry(rng, params, disparity, sat, valid)
        self.tries.append(found)
        return found

    def measure_lr(self, t: RangeTry) -> None:
        if t.lr_share is None:
            checked = left_right_check(t.disparity, self.right(t.params), LR_TOLERANCE_PX)
            t.lr_share = float(np.isfinite(checked[self.usable]).mean()) if self.usable.any() else 0.0


def search(matcher: Matcher, rng: SearchRange) -> RangeTry:
    """Match over `rng`; a range the tool chose is widened on its saturated sides (within the bounds, at most
    MAX_WIDENINGS times, each from the last try) and a wider try replaces the one kept only if neither share
    falls; returns the try kept (all are in matcher.tries, each with its verdict)."""
    kept = last = matcher.run(rng)
    while not rng.user and last.rng.widened < MAX_WIDENINGS:
        grown = widened(last.rng, last.sat, matcher.bounds)
        if grown is None:
            break
        matcher.measure_lr(kept)
        last = matcher.run(grown)
        matcher.measure_lr(last)
        if last.valid_share < kept.valid_share or last.lr_share < kept.lr_share:
            last.verdict = (f"not kept: against {kept.rng.min_disparity}..{kept.rng.max_disparity} px valid "
                            f"{100 * kept.valid_share:.1f}% -> {100 * last.valid_share:.1f}%, left-right consistent "
                            f"{100 * kept.lr_share:.1f}% -> {100 * last.lr_share:.1f}%")
            continue
        kept.verdict = f"replaced by {grown.min_disparity}..{grown.max_disparity} px, which explained no less"
        kept = last
    kept.verdict = "kept"
    return kept


def refusal_note(matcher: Matcher, kept: RangeTry) -> str:
    """Why a saturated range kept was not widened further, for the warning ('' when nothing was refused)."""
    refused = [t for t in matcher.tries if t.verdict.startswith("not kept")]
    if refused:
        return "; wider ranges were tried and " + "; ".join(
            f"{t.rng.min_disparity}..{t.rng.max_disparity} px {t.verdict}" for t in refused)
    b = matcher.bounds
    at_low = kept.sat.low and kept.rng.min_disparity <= b.low
    at_high = kept.sat.high and kept.rng.max_disparity >= b.high
    if at_low or at_high:
        return f"; the range is at the rig's disparity bounds {b.low}..{b.high} px ({b.detail})"
    return ""
