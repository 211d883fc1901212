"""Rectification of pairs with a fisheye camera vs live OpenCV (cv2.fisheye.stereoRectify,
cv2.fisheye.initUndistortRectifyMap, cv2.initUndistortRectifyMap, cv2.fisheye.undistortPoints), the pinhole path
unchanged, the field kept, and the refusals."""

import cv2
import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.models.pose import rodrigues
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.stereo.rectify import rectify_calibration
from dstereo.stereo.rectify_fisheye import (MAX_HALF_FIELD_DEG, field_of_view, lens_map, rectification_maps,
                                            rectify_any, stereo_rectify_lenses)
from dstereo.synth import fisheye_rig

SIZE = (640, 480)


def _calib(rig) -> StereoCalibration:
    R, T = rig.rotation_translation()
    return StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(), rig.right.coeffs(), R, T,
                             rig.left.image_size, models=(rig.left.lens, rig.right.lens))


FISHEYE = _calib(fisheye_rig())
MIXED = _calib(fisheye_rig(mixed=True))


def _swapped(c: StereoCalibration) -> StereoCalibration:
    """The same rig seen from its other camera: the right camera of this one is the left of that, so the camera
    whose rectified focal is the smaller changes sides (cv2.fisheye gives both the smaller one)."""
    R, T = np.asarray(c.R), np.asarray(c.T).reshape(3)
    return StereoCalibration(c.K2, c.D2, c.K1, c.D1, R.T, -R.T @ T, c.image_size, models=c.models[::-1])


def _rel(ours, ref) -> float:
    ours, ref = np.asarray(ours, float), np.asarray(ref, float)
    return float(np.abs(ours - ref).max() / np.abs(ref).max())


@pytest.mark.numerics
@pytest.mark.parametrize("side", ["as built", "swapped"])
@pytest.mark.parametrize("zero_disparity", [True, False])
@pytest.mark.parametrize("balance", [0.0, 0.5, 1.0])
def test_fisheye_pair_matches_cv2_fisheye_stereo_rectify(balance, zero_disparity, side):
    c = FISHEYE if side == "as built" else _swapped(FISHEYE)
    ours = rectify_any(c, SIZE, alpha=balance, zero_disparity=zero_disparity)
    flags = cv2.CALIB_ZERO_DISPARITY if zero_disparity else 0
    ref = cv2.fisheye.stereoRectify(c.K1, c.D1[:4], c.K2, c.D2[:4], SIZE, c.R, c.T.reshape(3, 1), flags,
                                    balance=balance, fov_scale=1.0)
    # Both evaluate the same double-precision formulas. cv2 stops its Newton inverse of the edge midpoints once a
    # step is below 1e-8 rad; convergence is quadratic, so what is left is ~1e-16 rad, amplified a few times by the
    # focal rule (1 / (cn - min)); R1, R2 differ only in atan2 vs acos for one angle (1e-15 at this 4.6 deg).
    for name, a, b in zip(("R1", "R2", "P1", "P2", "Q"), (ours.R1, ours.R2, ours.P1, ours.P2, ours.Q), ref):
        assert _rel(a, b) < 1e-12, name


@pytest.mark.numerics
def test_fisheye_maps_match_cv2_where_both_are_defined():
    c = FISHEYE
    rect = rectify_any(c, SIZE, alpha=1.0, zero_disparity=False)
    maps = rectification_maps(c, rect)
    for (mx, my), K, D, R, P in zip(maps, (c.K1, c.K2), (c.D1, c.D2), (rect.R1, rect.R2), (rect.P1, rect.P2)):
        rx, ry = cv2.fisheye.initUndistortRectifyMap(K, D[:4], np.asarray(R), np.asarray(P), rect.size, cv2.CV_32FC1)
        both = np.isfinite(mx) & np.isfinite(rx)
        assert both.mean() > 0.99
        # cv2 returns float32 maps: half a float32 step of the largest coordinate, plus our own double rounding
        tol = np.abs(rx[both]).max() * 2.0 ** -24 + 1e-9
        assert np.abs(mx - rx)[both].max() <= tol and np.abs(my - ry)[both].max() <= tol
        assert not np.isfinite(mx[~np.isfinite(rx)]).any()  # behind the camera for cv2: no source for us either


@pytest.mark.numerics
def test_mixed_rig_maps_and_rows_against_opencv():
    """A pinhole left and a fisheye right: each map equals OpenCV's own map for that lens with the same R and P,
    and a scene point lands on the same rectified row in both images (OpenCV's projections and inverses)."""
    c = MIXED
    rect = rectify_any(c, SIZE, alpha=0.0, zero_disparity=False)
    (lx, ly), (fx, fy) = rectification_maps(c, rect)
    rx, ry = cv2.initUndistortRectifyMap(c.K1, c.D1, np.asarray(rect.R1), np.asarray(rect.P1), rect.size,
                                         cv2.CV_32FC1)
    tol = np.abs(rx).max() * 2.0 ** -24 + 1e-9  # float32 output, as above
    assert np.abs(lx - rx).max() <= tol and np.abs(ly - ry).max() <= tol
    rx, ry = cv2.fisheye.initUndistortRectifyMap(c.K2, c.D2[:4], np.asarray(rect.R2), np.asarray(rect.P2),
                                                 rect.size, cv2.CV_32FC1)
    both = np.isfinite(fx) & np.isfinite(rx)
    assert np.abs(fx - rx)[both].max() <= tol and np.abs(fy - ry)[both].max() <= tol
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-150, 150, 50), rng.uniform(-100, 100, 50), rng.uniform(400, 900, 50)]
    q1 = cv2.projectPoints(p, np.zeros(3), np.zeros(3), c.K1, c.D1)[0]
    q2 = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), cv2.Rodrigues(c.R)[0], c.T, c.K2, c.D2[:4])[0]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    r1 = cv2.undistortPoints(q1, c.K1, c.D1, R=np.asarray(rect.R1), P=np.asarray(rect.P1), criteria=crit).reshape(-1, 2)
    r2 = cv2.fisheye.undistortPoints(q2, c.K2, c.D2[:4], R=np.asarray(rect.R2), P=np.asarray(rect.P2),
                                     criteria=crit).reshape(-1, 2)
    # rows agree to the inverses' convergence (1e-14 normalised, ~1e-11 px at f ~ 300 px; 1e-8 px is generous)
    assert np.abs(r1[:, 1] - r2[:, 1]).max() < 1e-8


def test_pinhole_pairs_keep_the_bouguet_path_bit_for_bit():
    K1 = np.array([[800.0, 0, 330], [0, 805, 250], [0, 0, 1]])
    K2 = np.array([[900.0, 0, 310], [0, 898, 235], [0, 0, 1]])
    D = np.array([-0.2, 0.1, 0.001, -0.002, 0.0, 0, 0, 0])
    c = StereoCalibration(K1, D, K2, D, np.asarray(rodrigues(np.array([0.02, -0.05, 0.01]))), np.array([-120.0, 3, 4]))
    ours, ref = rectify_any(c, SIZE, alpha=0.3), rectify_calibration(c, SIZE, alpha=0.3)
    for name in ("R1", "R2", "P1", "P2", "Q", "roi1", "roi2"):
        assert np.array_equal(np.asarray(getattr(ours, name)), np.asarray(getattr(ref, name))), name


def test_field_of_view_and_the_wide_lens_clamp():
    """balance 1 keeps a wider field than 0; a lens seeing more than 2 x MAX_HALF_FIELD_DEG across its edge
    midpoints, forced to a pinhole rectification, is pulled in to that field at balance 0 (OpenCV's rule is
    undefined there), and stays under 180 degrees at balance 1; left to choose, it gets the spherical one."""
    narrow = field_of_view(rectify_any(FISHEYE, SIZE, alpha=0.0))
    wide = field_of_view(rectify_any(FISHEYE, SIZE, alpha=1.0))
    assert 90.0 < narrow["horizontal_deg"] < wide["horizontal_deg"] < 2 * MAX_HALF_FIELD_DEG
    left, right = FISHEYE.cameras()
    wider = type(left)(left.k * np.array([0.55, 0.55, 1, 1]), left.dist, left.image_size)  # ~230 deg across
    for balance, limit in ((0.0, 2 * MAX_HALF_FIELD_DEG), (1.0, 180.0)):
        assert stereo_rectify_lenses(wider, wider, FISHEYE.rig, SIZE, balance=balance).projection == "spherical"
        rect = stereo_rectify_lenses(wider, wider, FISHEYE.rig, SIZE, balance=balance, projection="pinhole")
        fov = field_of_view(rect)
        assert np.isfinite(np.asarray(rect.P1)).all() and 120.0 < fov["horizontal_deg"] <= limit + 1e-9
        mx, _ = lens_map(wider.k, wider.dist.coeffs, rect.R1, rect.P1, "fisheye", rect.size)
        assert np.isfinite(np.asarray(mx)).all()  # every rectified ray is inside the lens's 230 deg


def _with(c: StereoCalibration, **changes) -> StereoCalibration:
    from dataclasses import replace

    return replace(c, **changes)


_R30 = np.asarray(rodrigues(np.array([0.0, np.radians(30.0), 0.0])))
# a 128-degree fisheye beside an 18-degree pinhole looking 30 degrees away: the rectified pair keeps the fisheye's
# field and the pinhole's principal point of its own focal length (cv2.fisheye's rule), so no rectified pixel
# sees the pinhole's image
_NARROW = dict(K2=np.array([[2000.0, 0, 320], [0, 2000, 240], [0, 0, 1]]), D2=np.zeros(8), R=_R30,
               T=-_R30 @ np.array([120.0, 0, 0]), models=("fisheye", "pinhole"))


@pytest.mark.parametrize("change, message", [
    (_NARROW, "the rectified field would be empty: no rectified pixel of the right camera sees its image"),
    (dict(R=np.asarray(rodrigues(np.array([0.0, np.radians(120.0), 0.0])))), "optical axes are 120.0 deg apart"),
    (dict(K1=MIXED.K1, D1=np.array([-0.6, 0, 0, 0, 0, 0, 0, 0]), models=("pinhole", "fisheye")),
     "left lens model has no ray for an image edge midpoint .its distortion is not invertible"),
    (dict(T=np.zeros(3)), "baseline T is zero"),
])
def test_bad_fisheye_rigs_are_one_line_errors(change, message):
    with pytest.raises(DstereoError, match=message) as err:
        rectify_any(_with(FISHEYE, source="rig.yml", **change), SIZE, zero_disparity=False)
    assert "\n" not in str(err.value) and "rig.yml" in str(err.value)


def test_a_fisheye_folding_inside_its_image_is_rectified_from_its_field():
    """k1 = -0.5 folds at theta = sqrt(2/3) rad (47 deg, theta_d' = 1 - 1.5 theta^2 = 0), 158 px from the centre:
    no image edge midpoint has a ray. The field is taken to the fold (where the lens's rays end), not refused."""
    c = _with(FISHEYE, D2=np.array([-0.5, 0, 0, 0, 0, 0, 0, 0]))
    rect = rectify_any(c, SIZE)
    assert rect.projection == "pinhole" and "right lens has no ray at 4 of its image edge midpoints" in rect.why
    assert f"{np.degrees(np.sqrt(2 / 3)):.0f} deg off its axis (its polynomial's fold)" in rect.why
    (lx, ly), (rx, ry) = rectification_maps(c, rect)
    x, y, w, h = (int(v) for v in np.asarray(rect.roi2))
    inside = np.isfinite(rx) & (rx >= 0) & (rx <= SIZE[0] - 1) & (ry >= 0) & (ry <= SIZE[1] - 1)
    assert inside.any() and inside[y + h // 2, x + w // 2]  # the right camera's field lies in its rectified image


def test_the_corners_reach_sets_a_folding_lens_field_in_a_pinhole_rectification():
    """With stereo.yml's corner_angle_max2 = 35 deg (inside the fold at 47), the right camera's four edge-midpoint
    rays are taken at 35 deg off its axis in their azimuths, and its rectified column follows the module's rule
    (cv2.fisheye.estimateNewCameraMatrixForUndistortRectify's, balance 0), recomputed here from those rays alone:
    the mean of the four on z = 1 after R2, and the largest of the four focal lengths that put each on its image
    edge: cx = w/2 - mean_x f. Closed form on O(100) px values, so 1e-6 px; the fold's field puts the column
    2.4 px elsewhere (the field must not ignore the reach)."""
    from dataclasses import replace

    c = _with(FISHEYE, D2=np.array([-0.5, 0, 0, 0, 0, 0, 0, 0]))
    reached = rectify_any(replace(c, extras={"corner_angle_max2": 35.0}), SIZE, zero_disparity=False)
    folded = rectify_any(c, SIZE, zero_disparity=False)
    assert "35 deg off its axis (the corners' reach)" in reached.why
    w, h = SIZE
    K = np.asarray(c.K2, float)
    q = np.array([[w // 2, 0], [w, h // 2], [w // 2, h], [0, h // 2]], float)
    xy = (q - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
    cs = xy / np.linalg.norm(xy, axis=1, keepdims=True)
    e = np.radians(35.0)
    rays = np.column_stack([np.sin(e) * cs, np.full(4, np.cos(e))]) @ np.asarray(reached.R2).T
    aspect = K[0, 0] / K[1, 1]
    pts = rays[:, :2] / rays[:, 2:] * [1.0, aspect]
    cn, lo, hi = pts.mean(axis=0), pts.min(axis=0), pts.max(axis=0)
    f = max(w / 2 / (cn[0] - lo[0]), w / 2 / (hi[0] - cn[0]), h / 2 * aspect / (cn[1] - lo[1]),
            h / 2 * aspect / (hi[1] - cn[1]))
    cx = float(np.asarray(reached.P2)[0, 2])
    assert abs(cx - (w / 2 - cn[0] * f)) < 1e-6, (cx, w / 2 - cn[0] * f)
    assert abs(cx - float(np.asarray(folded.P2)[0, 2])) > 1.0


def test_the_pinhole_rectification_refuses_a_fisheye_camera():
    from dstereo.stereo.rectify import stereo_rectify

    with pytest.raises(DstereoError, match="the right camera is a fisheye"):
        stereo_rectify(*MIXED.cameras(), MIXED.rig, SIZE)
