"""The default's rule for views lit alike (issue 30): the grey levels' map checked by the rank cost's
(`dstereo.stereo.cost_check`), and which maps the default fills (`dstereo.stereo.fill.fill_wanted`); on synthetic
maps with a known drift, and on the shared Middlebury scene it was made for where the data are present."""

from dataclasses import replace

import cv2
import numpy as np

from conftest import require_data
from dstereo.io.calib_files import read_middlebury_calib, read_pfm
from dstereo.io.images import read_image
from dstereo.stereo.cost_check import cross_checked, region_px
from dstereo.stereo.fill import fill_wanted
from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated

H, W = 200, 260
VOTES = 10  # the fewest pixels matched by both for a window to vote (the pipeline passes SGBM's speckle window)
DRIFT = (slice(60, 140), slice(80, 180))  # the region where the grey levels' map is off by 5 px


def _maps(seed: int = 0, rank_share: float = 0.03, stray_share: float = 0.002):
    """(grey-level map, rank map, drifted mask): a plane of 20 px matched everywhere by the grey levels, 5 px off
    over DRIFT; the rank cost matches `rank_share` of the pixels at random, at the true disparity (so it disagrees
    inside DRIFT), plus `stray_share` of isolated pixels 8 px off anywhere (its own mismatches)."""
    rng = np.random.default_rng(seed)
    truth = np.full((H, W), 20.0, np.float32)
    grey_map = truth.copy()
    drifted = np.zeros((H, W), bool)
    drifted[DRIFT] = True
    grey_map[drifted] += 5.0
    rank_map = np.where(rng.random((H, W)) < rank_share, truth, np.nan).astype(np.float32)
    stray = rng.random((H, W)) < stray_share
    rank_map[stray] = truth[stray] + 8.0
    return grey_map, rank_map, drifted


def test_a_region_the_rank_cost_mostly_contradicts_is_dropped_isolated_disagreements_are_kept():
    """Inside the drifted region (beyond half a window from its rim, where the vote is the region's own) every
    grey-level match is dropped, the ones the rank cost never matched included; a window's length away from it
    none is, though the rank cost's own strays disagree there (isolated: each window holds a few agreeing votes
    against one); the summary's shares are the masks' counts."""
    grey_map, rank_map, drifted = _maps()
    checked, figures = cross_checked(grey_map, rank_map, np.ones((H, W), bool), VOTES)
    size = region_px(W)
    assert figures["region_px"] == size == 37  # a seventh of 260 px, odd
    half = size // 2
    inner = np.zeros((H, W), bool)
    inner[DRIFT[0].start + half: DRIFT[0].stop - half, DRIFT[1].start + half: DRIFT[1].stop - half] = True
    far = ~cv2.dilate(drifted.astype(np.uint8), np.ones((2 * size + 1,) * 2, np.uint8)).astype(bool)
    assert np.isnan(checked[inner]).all()
    assert np.isfinite(checked[far]).all()
    assert ((np.abs(rank_map - grey_map) > 1) & far).sum() > 20  # the strays were there to be kept
    assert figures["dropped_share"] == np.isnan(checked).mean()
    assert figures["disagree_share"] == (np.abs(rank_map - grey_map) > 1).mean()


def test_where_the_rank_cost_matched_next_to_nothing_the_grey_levels_stand():
    """Fewer than `min_votes` pixels matched by both in every window: the rank cost says nothing there, and the
    grey-level map is kept whole, drift and all (the check cannot see it: the default's limit); with the votes
    there, the same disagreement drops the region."""
    grey_map, _, _ = _maps()
    rank_map = np.full((H, W), np.nan, np.float32)
    rank_map[98:101, 128:131] = 20.0  # a blob of 9 votes inside the drifted region, against it
    checked, figures = cross_checked(grey_map, rank_map, np.ones((H, W), bool), VOTES)
    assert np.array_equal(checked, grey_map) and figures["dropped_share"] == 0.0
    checked, figures = cross_checked(grey_map, rank_map, np.ones((H, W), bool), 9)
    assert np.isnan(checked[100, 130]) and figures["dropped_share"] > 0


def test_the_default_fills_the_rank_costs_maps_only_and_the_flags_force_it():
    """`fill` None (the default) fills a map matched on the rank transform and not one matched on the grey levels;
    True / False are kept whatever the cost; the reason is said."""
    rank = {"search_range": {"matching_cost": {"cost": "rank"}}}
    grey = {"search_range": {"matching_cost": {"cost": "intensity", "checked_by": "rank"}}}
    default = ReconstructionConfig()
    assert default.fill is None
    assert fill_wanted(default, rank)[0] and not fill_wanted(default, grey)[0]
    for forced in (True, False):
        for summary in (rank, grey):
            wanted, why = fill_wanted(replace(default, fill=forced), summary)
            assert wanted is forced and why.startswith("given")
    assert "auto" in fill_wanted(default, rank)[1] and "auto" in fill_wanted(default, grey)[1]


def test_middlebury_piano_as_it_is_meets_the_issue_with_no_flags():
    """Piano as it is (its views lit alike: the grey levels, the check, no fill): median <= 1 %, p90 <= 5 %,
    density >= 80 % (the grey levels unchecked: p90 5.11 % over the blank wall; measured with the check: p90
    3.00 %, density 86.4 %, 3.1 % of the pixels dropped); `--cost intensity` is the map before the check, which
    keeps every pixel the check kept."""
    folder = require_data("middlebury2014q") / "Piano"
    calib = read_middlebury_calib(folder / "calib.txt")
    left, right = read_image(folder / "im0.png"), read_image(folder / "im1.png")
    config = ReconstructionConfig(uncertainty=False)
    result = reconstruct_calibrated(calib, left, right, config, "Piano")
    cost = result.summary["search_range"]["matching_cost"]
    assert cost["cost"] == "intensity" and cost["checked_by"] == "rank" and cost["cross_check"]["dropped_share"] > 0
    assert result.filled is None and not result.summary["fill"]["enabled"]
    gt = read_pfm(folder / "disp0GT.pfm").astype(float)
    nocc = (cv2.imread(str(folder / "mask0nocc.png"), cv2.IMREAD_GRAYSCALE) == 255) & np.isfinite(gt)
    z_gt = calib.K1[0, 0] * calib.baseline / (gt + calib.extras["doffs"])
    est = nocc & np.isfinite(result.depth)
    rel = np.abs(result.depth - z_gt)[est] / z_gt[est]
    print(f"Piano as is, default: median {100 * np.median(rel):.2f} %, p90 {100 * np.percentile(rel, 90):.2f} %, "
          f"density {100 * est.sum() / nocc.sum():.1f} %, dropped {100 * cost['cross_check']['dropped_share']:.1f} %")
    assert np.median(rel) <= 0.01 and np.percentile(rel, 90) <= 0.05 and est.sum() >= 0.8 * nocc.sum()
    plain = reconstruct_calibrated(calib, left, right, replace(config, matching_cost="intensity"), "Piano")
    kept = np.isfinite(result.disparity)
    assert np.array_equal(result.disparity[kept], plain.disparity[kept])
    assert np.isfinite(plain.disparity).sum() > kept.sum()
