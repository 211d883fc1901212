"""The SGBM search range (issue 14): `disparity_range` by hand, the range sources, the estimate from sparse
matches on pairs whose true range is known (a rendered converging rig with negative disparities, a Middlebury
scene upscaled 2x), saturation detected and widened, and Middlebury files as they are published."""

import numpy as np
import pytest

from conftest import require_data
from dstereo.stereo.disparity import disparity_range
from dstereo.errors import DstereoError
from dstereo.stereo.range_bounds import width_bounds
from dstereo.stereo.search_range import (SearchRange, from_bounds, from_middlebury, from_sparse, saturation,
                                  sparse_disparities, widened)

# --- disparity_range: expected values worked out by hand (d = f B / Z - doffs) --------------------------------
# f = 1000 px, B = 64 mm: Z = 1000 mm -> d = 64 px, Z = 2000 mm -> d = 32 px (exact in binary floating point).
CASES = [
    # doffs, margin, expected (lo, num), why
    (0.0, 0.0, (32, 48), "32..64 holds 33 values: ceil(33 / 16) = 3 blocks (without the +1: 32 -> 2 blocks)"),
    (0.5, 0.0, (31, 48), "31.5..63.5: floor(31.5) = 31 (ceil would give 32); 31..64 = 34 values"),
    (0.5, 2.0, (29, 48), "29.5..65.5 with the margin: floor 29, ceil 66, 38 values"),
    (40.0, 0.0, (-8, 48), "-8..24: a converging rig's negative disparities stay (33 values)"),
    (-0.25, 0.0, (32, 48), "32.25..64.25 -> 32..65 = 34 values"),
]


@pytest.mark.parametrize("doffs, margin, expected, why", CASES)
def test_disparity_range_by_hand(doffs, margin, expected, why):
    assert disparity_range(1000.0, 64.0, 1000.0, 2000.0, doffs=doffs, margin=margin) == expected, why


def test_disparity_range_minimum_and_bad_input():
    assert disparity_range(1000.0, 64.0, 1900.0, 2000.0) == (32, 16)  # 32..34: 3 values, one block of 16
    for z in ((2000.0, 1000.0), (0.0, 1000.0), (1000.0, 1000.0)):
        with pytest.raises(DstereoError, match="depth range"):
            disparity_range(1000.0, 64.0, *z)
    with pytest.raises(DstereoError, match="positive"):
        disparity_range(-1000.0, 64.0, 1000.0, 2000.0)


def test_range_sources_by_hand():
    r = from_bounds(-3.5, 60.2, "x")
    assert (r.min_disparity, r.num_disparities, r.max_disparity) == (-4, 80, 75)  # -4..61 = 66 values -> 80
    m = from_middlebury({"ndisp": 73.0, "vmin": 8.0, "vmax": 65.0})
    assert (m.min_disparity, m.max_disparity, m.source) == (0, 79, "calib.txt ndisp")  # 0..72 -> 80 values
    v = from_middlebury({"vmin": 8.0, "vmax": 65.0})  # margin max(2, 5.7) px
    assert (v.min_disparity, v.max_disparity) == (2, 81)  # 2.3..70.7 -> 2..71 = 70 values -> 80
    assert from_middlebury({}) is None
    assert from_sparse(np.arange(10.0), 640) is None  # too few matches: no estimate
    # 0.5..99.5 % of 0..100 = 0.5..99.5, margin 30 % of 99 = 29.7 -> -29.2..129.2 -> -30..130 = 161 -> 176
    s = from_sparse(np.linspace(0.0, 100.0, 1001), 640)
    assert (s.min_disparity, s.num_disparities) == (-30, 176)


def test_saturation_and_widening():
    rng = SearchRange(0, 64, "sparse matches")
    d = np.full((10, 100), 30.0)
    d[0, :5] = 63.2  # 5 of 1000 valid pixels at the top end: 0.5 %, under the 1 % limit
    d[1, :] = np.nan
    sat = saturation(d, rng)
    assert sat.high_share == pytest.approx(5 / 900) and not sat.saturated
    assert sat.invalid_share == pytest.approx(0.1)
    d[2, :] = 62.5  # now 105 of 900 within 1 px of the top
    sat = saturation(d, rng)
    assert sat.high and not sat.low
    grown = widened(rng, sat, width_bounds(640))
    assert (grown.min_disparity, grown.max_disparity, grown.widened) == (0, 127, 1)
    assert widened(SearchRange(-639, 1280, "x"), sat, width_bounds(640)) is None  # all a 640 px wide image holds


# --- estimates on pairs whose true range is known ------------------------------------------------------------


@pytest.fixture(scope="module")
def converging_pair():
    """A tilted sample 640 mm from the reduced Plasmatron rig (aimed at 600 mm): behind the rectified
    zero-disparity plane, so its disparities are negative. Rendered at 240 x 180."""
    from dstereo.io.calib_files import StereoCalibration
    from dstereo.jobs.synthetic_recession import sample_truth
    from dstereo.synth import Sample, plasmatron_rig, sample_pose
    from dstereo.synth.scenes import sample_pair

    size = (240, 180)
    rig = plasmatron_rig(size, 4800.0 * size[0] / 640)
    sample = Sample()
    pose = sample_pose(sample.length, distance_mm=640.0, yaw_deg=12.0)
    render = sample_pair(rig, sample, pose, seed=0)
    r, t = rig.rotation_translation()
    calib = StereoCalibration(np.asarray(rig.left.matrix()), np.asarray(rig.left.coeffs()),
                              np.asarray(rig.right.matrix()), np.asarray(rig.right.coeffs()), np.asarray(r),
                              np.asarray(t), size, source="rendered rig")
    return render, calib, sample_truth(rig, sample, pose)


def _true_disparities(render, calib, result):
    """Sign-normalised disparities of the rendered surface's pixels, from the render's depth and the Q used."""
    from dstereo.synth.rays import camera_rays
    from dstereo.synth.truth import camera_from_truth

    depth = render.truth_left["depth"]
    xy = np.asarray(camera_rays(camera_from_truth(render.truth_left["camera"]), 1))[:, :, 0, :]
    points = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2)[np.isfinite(depth)] * \
        depth[np.isfinite(depth)][:, None]
    z_rect = (points @ result.matrices["R1"].T)[:, 2]
    Q = result.matrices["Q"]
    return (Q[2, 3] / z_rect - Q[3, 3]) / abs(Q[3, 2])


def test_converging_rig_range_holds_its_negative_disparities(converging_pair):
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated

    render, calib, _ = converging_pair
    # The grey-level cost (issue 30's rank cost keeps -33..14 px here: its widening to -81 lost 0.08 % of the
    # valid share and was refused, leaving 3.6 % of the pixels at the low end; range_tries' rule, not the range)
    result = reconstruct_calibrated(calib, render.left, render.right,
                                    ReconstructionConfig(uncertainty=False, matching_cost="intensity"))
    true = _true_disparities(render, calib, result)
    assert np.percentile(true, 99) < 0  # the surface lies behind the zero-disparity plane
    s = result.summary["search_range"]
    assert s["source"] == "sparse matches" and not s["saturation"]["saturated_low"]
    assert s["min_disparity"] <= true.min() and true.max() <= s["max_disparity"]
    assert s["depth_range_mm"]["near"] < 600 and s["depth_range_mm"]["far"] > 700
    # the old default, 0..63 px, holds none of it: almost all of the surface lost
    old = reconstruct_calibrated(calib, render.left, render.right, ReconstructionConfig(
        uncertainty=False, sgbm_user=("min_disparity", "num_disparities")))
    seen = np.isfinite(render.truth_left["depth"])
    assert np.isfinite(result.disparity[seen]).mean() > 0.8 > 0.2 > np.isfinite(old.disparity[seen]).mean()
    assert any("runs off the disparity search range" in w for w in old.warnings)


def test_middlebury_upscaled_2x_range_from_the_pair():
    import cv2

    from dstereo.io.calib_files import read_pfm
    from dstereo.io.images import read_image

    scene = require_data("middlebury2014q") / "Adirondack"
    up = [cv2.resize(read_image(scene / n), None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
          for n in ("im0.png", "im1.png")]
    gt = 2.0 * read_pfm(scene / "disp0GT.pfm")
    gt = gt[np.isfinite(gt)]
    est = from_sparse(sparse_disparities(*up, 1.0), up[0].shape[1])
    lo, hi = np.percentile(gt, [0.5, 99.5])  # measured 20..124 px; the sparse 0.5-99.5 % is 22..96
    assert est.min_disparity <= lo and hi <= est.max_disparity
    assert est.num_disparities <= 2 * (hi - lo)  # and not absurdly wide


# --- saturation after matching ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def teddy():
    from dstereo.io.calib_files import read_middlebury_calib
    from dstereo.io.images import read_image

    scene = require_data("middlebury2014q") / "Teddy"  # ground truth 15..53 px
    return read_middlebury_calib(scene / "calib.txt"), read_image(scene / "im0.png"), read_image(scene / "im1.png")


def test_a_users_short_range_is_kept_with_a_warning(teddy):
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
    from dstereo.stereo.disparity import SGBMParams

    calib, left, right = teddy
    config = ReconstructionConfig(sgbm=SGBMParams(num_disparities=32), sgbm_user=("num_disparities",),
                                  uncertainty=False)
    result = reconstruct_calibrated(calib, left, right, config)
    s = result.summary["search_range"]
    assert (s["min_disparity"], s["max_disparity"], s["user"], s["widened"]) == (0, 31, True, 0)
    assert s["saturation"]["saturated_high"]
    assert any("runs off the disparity search range 0..31" in w and "--z-min/--z-max" in w for w in result.warnings)
    # and independently of SGBM: most sparse matches (the scene's 15..53 px) lie above the range
    assert s["sparse_check"]["above_share"] > 0.3
    assert any("sparse matches lie outside the disparity search range 0..31" in w for w in result.warnings)


def test_a_short_estimated_range_is_widened(teddy):
    from dstereo.stereo.reconstruct import ReconstructionConfig, match_in_range

    calib, left, right = teddy
    Q = np.array([[1, 0, 0, -calib.K1[0, 2]], [0, 1, 0, -calib.K1[1, 2]], [0, 0, 0, calib.K1[0, 0]],
                  [0, 0, 1 / calib.baseline, calib.extras["doffs"] / calib.baseline]])
    short = SearchRange(0, 32, "sparse matches")
    d, params, s, warnings = match_in_range("teddy", left, right, ReconstructionConfig(), Q,
                                            np.zeros(left.shape[:2], bool), estimate=short)
    assert s["widened"] >= 1 and s["max_disparity"] >= 53 and warnings == []
    assert s["tries"][0]["saturated_high"] and not s["saturation"]["saturated_high"]
    assert params.num_disparities == s["num_disparities"]


# --- Middlebury files as published ---------------------------------------------------------------------------


def test_doffs_within_the_files_rounding_is_accepted_and_used(tmp_path):
    from dstereo.io.calib_files import read_middlebury_calib

    text = "cam0=[1000.0 0 300.125; 0 1000.0 200; 0 0 1]\ncam1=[1000.0 0 347.687; 0 1000.0 200; 0 0 1]\n" \
           "doffs={}\nbaseline=100\nwidth=640\nheight=480\nndisp=64\n"
    path = tmp_path / "calib.txt"
    path.write_text(text.format("47.561"))  # cx1 - cx0 = 47.562: the official files round cx to 3 decimals
    calib = read_middlebury_calib(path)
    assert calib.K2[0, 2] - calib.K1[0, 2] == pytest.approx(47.561, abs=1e-12)  # depth goes through doffs
    path.write_text(text.format("47.58"))  # 0.018 px off: more than rounding
    with pytest.raises(DstereoError, match=r"doffs 47.58 differs from cx1 - cx0 = 47.562 by more than"):
        read_middlebury_calib(path)


# --- SGBM settings that follow the image ---------------------------------------------------------------------


def test_sgbm_settings_follow_the_image_unless_set():
    from dstereo.stereo.disparity import PRESETS, SGBMParams
    from dstereo.stereo.reconstruct import ReconstructionConfig, sized_sgbm, user_sgbm_names

    default = ReconstructionConfig()
    webcam = sized_sgbm(default.sgbm, user_sgbm_names(default), (480, 640))
    assert (webcam.block_size, webcam.speckle_window_size, webcam.penalties(1)) == (5, 100, (200, 800))
    big = sized_sgbm(default.sgbm, user_sgbm_names(default), (3000, 4000, 3))  # 12 Mpx: 100 x 39 -> capped
    assert (big.block_size, big.speckle_window_size, big.penalties(3)) == (9, 2000, (8 * 3 * 81, 32 * 3 * 81))
    mid = sized_sgbm(default.sgbm, user_sgbm_names(default), (1536, 2048))  # 3.1 Mpx: 100 x 10.24
    assert (mid.block_size, mid.speckle_window_size) == (7, 1024)
    # what the user set stays: named on the command line (even at the default's value), or a library caller's own
    named = ReconstructionConfig(sgbm_user=("block_size",))
    assert sized_sgbm(named.sgbm, user_sgbm_names(named), (3000, 4000)).block_size == 5
    own = ReconstructionConfig(sgbm=SGBMParams(speckle_window_size=50))
    assert sized_sgbm(own.sgbm, user_sgbm_names(own), (3000, 4000)).speckle_window_size == 50
    preset = ReconstructionConfig(sgbm=PRESETS["thesis-5.15"], sgbm_user=("preset",))
    assert sized_sgbm(preset.sgbm, user_sgbm_names(preset), (3000, 4000)) == PRESETS["thesis-5.15"]


def test_cli_and_config_files_record_what_the_user_set(tmp_path):
    from dstereo.config.reconstruction import build, flag_layer
    from dstereo.config.reconstruction import load_config

    assert build(flag_layer({"sgbm": ["blockSize=5", "num_disparities=64"]})).sgbm_user == ("block_size",
                                                                                           "num_disparities")
    assert build(flag_layer({"preset": "thesis-5.9"})).sgbm_user == ("preset",)
    path = tmp_path / "dstereo.toml"
    path.write_text("[sgbm]\nspeckleWindowSize = 100\n")
    assert load_config(path).sgbm_user == ("speckle_window_size",)


def test_false_matches_on_a_repeated_pattern_are_dropped():
    """A chessboard's repeated squares give same-row matches one square off: their disparity disagrees with their
    image neighbours' and they leave the estimate (otherwise the range would reach 30 px too far)."""
    from dstereo.stereo.search_range import consistent_with_neighbours

    q = np.stack(np.meshgrid(np.arange(0, 200, 10.0), np.arange(0, 100, 10.0)), axis=-1).reshape(-1, 2)
    d = np.full(len(q), 50.0) + 0.01 * q[:, 0]  # a slanted board: 50..52 px
    d[[7, 55, 130]] = 80.0  # one square (30 px) off
    keep = consistent_with_neighbours(q, d)
    assert not keep[[7, 55, 130]].any() and keep.sum() == len(q) - 3


# --- issue 14's own case: converging rig fx 4700 / 4900 px, 100 mm, 600 mm, tilted sample, no depth flags ----

@pytest.mark.slow
def test_converging_rig_of_the_issue_gets_the_whole_face(tmp_path):
    """At half size (fx 2350 / 2450 px, 320 x 240; 4 frames): `dstereo recession` without depth flags prints its
    range, reaches the face's negative disparities without saturating, and measures on the whole face. Before
    issue 14 (fixed 0..63 px) everything behind ~602 mm was dropped: 36 % of the face, the stagnation point
    2.7-3.7 mm off. The face share is counted on the true face (cells within head radius - 1.5 mm of the true
    stagnation point, in the tool's face frame), independent of the tool's own face mask."""
    import json

    from conftest import run_cli
    from dstereo.jobs.synthetic_recession import write_synthetic_sequence

    seq, out = tmp_path / "seq", tmp_path / "out"
    truth = write_synthetic_sequence(seq, n_frames=4, image_size=(320, 240), yaw_deg=12.0, focal_px=(2350.0, 2450.0))
    code, stdout, stderr = run_cli("recession", seq, "--calib", seq / "stereo.yml", "--out", out, "--grid", "1")
    assert code == 0, stderr
    assert "disparity search range" in stdout and "warning" not in stderr
    summary = json.loads((out / "summary.json").read_text())
    search = summary["search_range"]
    assert search["min_disparity"] < 0 and not search["saturation"]["saturated_low"]
    assert not search["saturation"]["saturated_high"]
    maps = np.load(out / "recession_maps.npz")
    u, v = np.meshgrid(maps["u_mm"], maps["v_mm"])
    e12 = np.array([summary["sample"]["e1"], summary["sample"]["e2"]])
    offset = np.array(truth["stagnation_point_mm"]) - np.array(summary["sample"]["stagnation_point_mm"])
    du, dv = e12 @ offset
    face = np.hypot(u - du, v - dv) <= truth["sample"]["head_radius"] - 1.5
    # Measured 99-100 % (the since-removed experiments/range_converging.py); a cut at the far side loses a third.
    assert np.isfinite(maps["heights_mm"][0][face]).mean() >= 0.95
    assert np.linalg.norm(offset) < 0.6  # measured 0.3-0.5 mm at 320 x 240 (the cut face: 2.7-3.7 mm)


# --- the calibration's board depths as a search-range prior --------------------------------------------------

def test_board_depth_prior_by_hand_and_from_the_file(tmp_path):
    """Boards at 400..800 mm, f = 1000 px, B = 100 mm (d = f B / Z): the prior spans 400 / 1.5 .. 800 * 1.5 mm
    = 266.7..1200 mm -> d = 83.3..375 px -> SGBM range 83 .. 83 + 304 - 1 (ceil(293 / 16) blocks of 16). The
    nodes are written by `append_board_depths` after `write_stereo_yml` and read back into the extras; a file
    without them gives no prior."""
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.stereo_files import append_board_depths, write_stereo_yml
    from dstereo.stereo.search_range import from_board_depths

    q = np.array([[1, 0, 0, -320], [0, 1, 0, -240], [0, 0, 0, 1000.0], [0, 0, 1 / 100.0, 0]])
    k = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
    path = write_stereo_yml(tmp_path / "stereo.yml", k, np.zeros(5), k, np.zeros(5), np.eye(3),
                            np.array([-100.0, 0, 0]), np.eye(3), np.eye(3), (640, 480))
    assert from_board_depths(read_stereo_calibration(path).extras, q, 640) is None
    append_board_depths(path, {"board_depth_min": 400.0, "board_depth_max": 800.0})
    calib = read_stereo_calibration(path)
    assert calib.extras["board_depth_min"] == 400.0 and calib.extras["board_depth_max"] == 800.0
    found = from_board_depths(calib.extras, q, 640)
    assert (found.min_disparity, found.num_disparities) == (83, 304)
    assert found.source == "calibration board depths"


def test_board_depth_prior_is_used_when_sparse_matches_are_too_few():
    """A textureless pair gives no sparse matches: with board depths in the calibration the range comes from
    them, without it is the default (with its warning)."""
    from dataclasses import replace

    from dstereo.io.calib_files import StereoCalibration
    from dstereo.stereo.reconstruct import ReconstructionConfig, initial_range

    q = np.array([[1, 0, 0, -320], [0, 1, 0, -240], [0, 0, 0, 1000.0], [0, 0, 1 / 100.0, 0]])
    flat = np.full((480, 640), 128, np.uint8)
    k = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
    calib = StereoCalibration(k, np.zeros(8), k, np.zeros(8), np.eye(3), np.array([-100.0, 0, 0]), (640, 480))
    plain = initial_range(ReconstructionConfig(), set(), q, flat, flat, calib)
    assert plain.source == "default"
    with_boards = replace(calib, extras={"board_depth_min": 400.0, "board_depth_max": 800.0})
    prior = initial_range(ReconstructionConfig(), set(), q, flat, flat, with_boards)
    assert prior.source == "calibration board depths" and (prior.min_disparity, prior.num_disparities) == (83, 304)


def test_board_depth_range_of_known_poses():
    """Corners 0..100 mm in x and y on the board: one pose 500 mm straight ahead (all at z = 500), one turned
    30 deg about y at 600 mm (z = 600 - x sin 30 deg = 550..600): the range is 500..600."""
    from types import SimpleNamespace

    from dstereo.io.stereo_files import board_depth_range

    xs, ys = np.meshgrid(np.linspace(0, 100, 5), np.linspace(0, 100, 4))
    obj = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    poses = np.array([[0, 0, 0, 0, 0, 500.0], [0, np.pi / 6, 0, 0, 0, 600.0]])
    found = board_depth_range(SimpleNamespace(poses=poses), obj)
    assert found["board_depth_min"] == pytest.approx(500.0) and found["board_depth_max"] == pytest.approx(600.0)
