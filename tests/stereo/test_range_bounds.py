"""The disparity search range bounded by the rig's geometry (issue 30): bounds by hand, and on renders of a parallel
rig (a textured board in front of a textured wall so far away that its disparity is ~0) a far background that no
longer widens the range past infinity, and a board that truly runs off the range and is still widened to."""

import numpy as np
import pytest

from dstereo.stereo.range_bounds import YAW_ERROR_RAD, geometric_bounds, width_bounds
from dstereo.stereo.search_range import EDGE_SHARE, Saturation, SearchRange, widened, within

F, B, W, H = 400.0, 100.0, 320, 240  # px, mm, px, px: the rendered parallel rig
WALL_MM = 1e6  # d = f B / Z = 0.04 px: at infinity within SGBM's 1/16 px steps
BOARD_MM = 350.0  # its centre; turned 0.6 rad about y, the board spans ~100..128 px


def _q(f: float, b: float, doffs: float = 0.0) -> np.ndarray:
    """Q of a rectified rig with focal f px, baseline b mm, principal points doffs px apart (Z = f b / (d + doffs))."""
    return np.array([[1, 0, 0, -160.0], [0, 1, 0, -120.0], [0, 0, 0, f], [0, 0, 1 / b, doffs / b]])


def test_geometric_bounds_by_hand():
    """f = 1000 px: infinity margin 1 px + 1000 * 1 mrad = 2 px. Parallel (doffs 0): infinity 0 -> low -2; width 640:
    -2..639 = 642 values -> 40 whole blocks of 16 -> high -2 + 640 - 1 = 637. Nearest board 900 mm -> 300 mm ->
    d = 1000 * 100 / 300 = 333.3 -> 334: -2..334 = 337 values -> 21 blocks -> high 333. Converging (doffs 40):
    infinity -40 -> low -42."""
    assert YAW_ERROR_RAD * 1000.0 == 1.0
    b = geometric_bounds(_q(1000.0, 100.0), 640)
    assert (b.low, b.high, b.infinity, b.near_mm) == (-2, 637, 0.0, None)
    near = geometric_bounds(_q(1000.0, 100.0), 640, {"board_depth_min": 900.0})
    assert (near.low, near.high, near.near_mm) == (-2, 333, 300.0)
    assert geometric_bounds(_q(1000.0, 100.0, doffs=40.0), 640).low == -42
    assert (width_bounds(640).low, width_bounds(640).high) == (-639, 624)  # 1264 = 79 blocks of the 1279 values


def test_ranges_are_cut_to_the_bounds_and_widened_inside_them():
    b = geometric_bounds(_q(1000.0, 100.0), 640, {"board_depth_min": 900.0})  # -2..333
    cut = within(SearchRange(-30, 400, "sparse matches"), b)
    assert (cut.min_disparity, cut.max_disparity) == (-2, 333)  # 336 = 21 blocks: the bounds exactly
    # 300..340 asks 48 values; 333 is the top, so the block is taken from below: 286..333
    top = within(SearchRange(300, 48, "x"), b)
    assert (top.min_disparity, top.max_disparity) == (286, 333)
    low = Saturation(0.05, 0.0, 0.5)
    # 59..106 grown by its 48 px on the low side would stop at 11, less than a step short of infinity: -2
    grown = widened(SearchRange(59, 48, "x"), low, b)
    assert (grown.min_disparity, grown.max_disparity, grown.widened) == (-2, 109, 1)
    # a low end that holds infinity: what piles there is background, nothing widens
    assert widened(SearchRange(0, 112, "x"), Saturation(0.05, 0.0, 0.5, low_at_infinity=True), b) is None
    assert not Saturation(0.05, 0.0, 0.5, low_at_infinity=True).saturated
    # the high side stops at the nearest depth allowed: 200..333 is 134 values -> 144, the extra 10 taken below
    high = widened(SearchRange(200, 112, "x"), Saturation(0.0, 0.05, 0.5), b)
    assert (high.min_disparity, high.max_disparity) == (190, 333)


@pytest.fixture(scope="module")
def scene():
    """The parallel rig's render, its calibration, rectifying maps and Q, the rectified pair and the true
    disparity of every left pixel (from the render's depth: identical distortion-free cameras side by side
    rectify with R1 = I, so the rectified depth is the camera's)."""
    import cv2

    from dstereo.io.calib_files import StereoCalibration
    from dstereo.models.camera import Camera
    from dstereo.stereo.reconstruct import rectifying_maps
    from dstereo.synth import Plane, stereo_rig
    from dstereo.synth.layered import Layer, layered_pair

    cam = Camera.create(F, F, (W - 1) / 2, (H - 1) / 2, image_size=(W, H))
    rig = stereo_rig(cam, cam, np.array([0, 0, 0, -B, 0, 0.0]))
    board = Layer(Plane(70.0, 52.5), np.array([0, 0.6, 0, 0, 0, BOARD_MM]), 2.8)  # speckle ~3 px
    wall = Layer(Plane(0.7 * WALL_MM, 0.55 * WALL_MM), np.array([0, 0, 0, 0, 0, WALL_MM]), 3 * WALL_MM / F)
    render = layered_pair(rig, [board, wall], seed=1)
    k = np.asarray(cam.matrix())
    calib = StereoCalibration(k, np.zeros(8), k, np.zeros(8), np.eye(3), np.array([-B, 0, 0]), (W, H),
                              source="rendered parallel rig")
    maps = rectifying_maps(calib, (W, H))
    # R = I and T along -x: R1 is I up to the rounding of O(1) entries (~1e-16)
    assert np.abs(np.asarray(maps.rect.R1) - np.eye(3)).max() < 1e-12
    Q = np.asarray(maps.rect.Q)
    rect = [cv2.remap(img, mx, my, cv2.INTER_LINEAR) for img, (mx, my) in zip((render.left, render.right), maps.remap)]
    true = (Q[2, 3] / render.truth_left["depth"] - Q[3, 3]) / abs(Q[3, 2])
    return render, calib, maps, Q, rect, true


def _match(scene, estimate, **kwargs):
    from dstereo.stereo.reconstruct import ReconstructionConfig, match_in_range

    _, calib, maps, Q, rect, _ = scene
    return match_in_range("render", *rect, ReconstructionConfig(), Q, maps.outside, calib, estimate=estimate, **kwargs)


def _board_range(scene):
    true = scene[5][scene[0].truth_left["layer"] == 0]
    return true.min(), true.max()


def test_far_background_keeps_the_range_inside_the_bounds(scene):
    """The board's sparse matches alone give 84..131 px (the issue's case: the background missed); the wall at
    ~0 px piles at the low end. The range is widened once, straight to the infinity bound, not past it, and the
    widening loses no valid share (measured 26.1 % -> 82.7 %). Without a known infinity (width bounds only) the
    same start is widened past it: the bound is what holds the range."""
    lo, hi = _board_range(scene)
    assert 84 < lo and hi < 131  # the start holds the board, not the wall
    _, _, s, warnings = _match(scene, SearchRange(84, 48, "sparse matches"))
    b = s["bounds"]
    assert b["infinity"] == 0.0 and b["low"] == -2  # 1 px + 400 px * 1 mrad = 1.4 px below 0
    assert all(b["low"] <= t["min_disparity"] and t["max_disparity"] <= b["high"] for t in s["tries"])
    assert (s["min_disparity"], s["widened"]) == (-2, 1) and warnings == []
    assert s["valid_share"] >= s["tries"][0]["valid_share"]
    assert s["lr_consistent_share"] >= s["tries"][0]["lr_consistent_share"]
    from dstereo.stereo.range_bounds import width_bounds as width_only

    _, _, unbounded, _ = _match(scene, SearchRange(84, 48, "sparse matches"), bounds=width_only(W))
    assert unbounded["tries"][-1]["min_disparity"] < b["low"]


def test_background_at_infinity_piled_at_the_low_end_is_not_widened_into(scene):
    """A range starting at 0 = infinity: the wall's pixels sit within 1 px of the low end (far above the 1 %
    limit), which is normal for a background at infinity: one try, no warning. With width bounds only (infinity
    unknown) the same start is taken for saturated and a widening below 0 is tried."""
    _, _, s, warnings = _match(scene, SearchRange(0, 144, "sparse matches"))
    assert s["saturation"]["low_share"] > 20 * EDGE_SHARE and s["saturation"]["low_at_infinity"]
    assert len(s["tries"]) == 1 and not s["saturation"]["saturated_low"] and warnings == []
    _, _, unbounded, _ = _match(scene, SearchRange(0, 144, "sparse matches"), bounds=width_bounds(W))
    assert len(unbounded["tries"]) >= 2 and unbounded["tries"][1]["min_disparity"] < 0


def test_a_scene_running_off_the_range_is_still_widened(scene):
    """-2..109 px holds the wall but not the board's near side (up to ~128 px): widened on the high side, kept
    (valid 67.8 % -> 82.6 %, left-right consistent 66.8 % -> 81.9 % measured), and the kept range holds the whole
    board, matched on over 90 % of its pixels (measured 95 %)."""
    render, *_, true = scene
    lo, hi = _board_range(scene)
    assert hi > 109
    d, _, s, warnings = _match(scene, SearchRange(-2, 112, "sparse matches"))
    assert s["tries"][0]["saturated_high"] and s["widened"] >= 1 and warnings == []
    assert s["min_disparity"] <= lo and hi <= s["max_disparity"] <= s["bounds"]["high"]
    assert s["valid_share"] > s["tries"][0]["valid_share"]
    assert s["lr_consistent_share"] > s["tries"][0]["lr_consistent_share"]
    board = render.truth_left["layer"] == 0
    assert np.isfinite(d[board]).mean() > 0.9


def test_the_nearest_board_of_the_calibration_caps_the_widening(scene):
    """Boards as near as 900 mm: nothing nearer than 300 mm, d <= 400 * 100 / 300 = 133.3 px -> -2..134 = 137
    values -> 8 blocks -> high 125. The board (up to ~128 px) runs past it: the range stops at 125 with a
    warning that names the bounds."""
    from dataclasses import replace

    _, calib, maps, Q, rect, _ = scene
    near = replace(calib, extras={"board_depth_min": 900.0})
    from dstereo.stereo.reconstruct import ReconstructionConfig, match_in_range

    _, _, s, warnings = match_in_range("render", *rect, ReconstructionConfig(), Q, maps.outside, near,
                                       estimate=SearchRange(-2, 112, "sparse matches"))
    assert s["bounds"]["high"] == 125 and s["max_disparity"] == 125
    assert len(warnings) == 1 and "disparity bounds -2..125" in warnings[0]


def test_reconstruct_chooses_its_own_range_inside_the_bounds(scene):
    """End to end, from the sparse matches: they see the wall (~0 px) and the board, the range starts at the
    infinity bound and needs no widening."""
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated

    render, calib, *_ = scene
    result = reconstruct_calibrated(calib, render.left, render.right, ReconstructionConfig(uncertainty=False))
    s = result.summary["search_range"]
    assert s["source"] == "sparse matches" and s["min_disparity"] == s["bounds"]["low"] == -2
    assert len(s["tries"]) == 1 and not s["saturation"]["saturated_high"]
    assert not any("search range" in w for w in result.warnings)
