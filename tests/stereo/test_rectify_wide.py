"""The spherical (epipolar equirectangular) rectification of `rectify_wide`, chosen by `rectify_fisheye` for fields
wider than a pinhole image holds: a scene point on the same row in both images, its disparity triangulated back
exactly by the two ray angles (where the pinhole Q is far off), the maps against the lens projection of the
point, the range rate against central differences, the choice and its refusals."""

import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.models import fisheye
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.stereo.rectify_fisheye import (MAX_HALF_FIELD_DEG, field_of_view, lens_map, rectification_maps,
                                            rectify_any, stereo_rectify_lenses)
from dstereo.stereo.rectify_wide import MAX_PSI_DEG
from dstereo.stereo.triangulate import (reproject, reproject_disparity, reproject_spherical, spherical_range_rate,
                                        to_original_left)
from dstereo.synth import fisheye_rig, wide_fisheye_rig


def _calib(rig) -> StereoCalibration:
    R, T = rig.rotation_translation()
    return StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(), rig.right.coeffs(), R, T,
                             rig.left.image_size, models=(rig.left.lens, rig.right.lens))


WIDE = _calib(wide_fisheye_rig())


@pytest.fixture(scope="module")
def rect():
    return rectify_any(WIDE)


def _angles_pixel(P, ray):
    """Rectified pixel (u, v) of a ray in a spherical rectified frame (the module's definition, written again)."""
    psi = np.arctan2(ray[0], np.hypot(ray[1], ray[2]))
    phi = np.arctan2(ray[1], ray[2])
    return np.array([P[0, 2] + P[0, 0] * psi, P[1, 2] + P[1, 1] * phi])


def _scene_points():
    """Points 300..2000 mm away, from straight ahead to 80 deg aside and 70 deg up or down (left camera frame)."""
    rng = np.random.default_rng(4)
    az, el = np.radians(rng.uniform(-80, 80, 200)), np.radians(rng.uniform(-70, 70, 200))
    v = np.stack([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)], axis=1)
    return v * rng.uniform(300.0, 2000.0, 200)[:, None]


def test_the_wide_rig_gets_the_spherical_rectification_and_says_why(rect):
    assert rect.projection == "spherical" and not rect.vertical
    assert f"more than a pinhole image holds ({MAX_HALF_FIELD_DEG:g} deg)" in rect.why
    assert "the left lens has no ray at 2 of its image edge midpoints" in rect.why  # left and right: past the fold
    fov = field_of_view(rect)
    # both lenses see past 90 deg to either side: the columns reach the MAX_PSI_DEG limit on both sides (to a grid
    # step of the sampled field), the rows the front half-space (+-90 deg)
    assert 2 * MAX_PSI_DEG - 3 < fov["horizontal_deg"] <= 2 * MAX_PSI_DEG + 1e-9
    assert 170.0 < fov["vertical_deg"] <= 180.0 + 1e-9
    # the pinhole rule of today, on a lens whose edge midpoints have rays within 75 deg: unchanged
    assert rectify_any(_calib(fisheye_rig())).projection == "pinhole"


def test_a_point_lies_on_one_row_and_its_disparity_triangulates_it(rect):
    """Rows are epipolar: the same v in both images, to rounding. The disparity's two ray angles give the point
    back to 1e-9 relative at any angle; the pinhole Q (what a spherical image's disparity is not) is off by tens
    of percent away from the axis, so a pipeline that used it would fail here."""
    R1, R2, P1, P2 = (np.asarray(getattr(rect, k)) for k in ("R1", "R2", "P1", "P2"))
    X = _scene_points()
    R, T = np.asarray(WIDE.R), np.asarray(WIDE.T).reshape(3)
    q1 = np.array([_angles_pixel(P1, R1 @ x) for x in X])
    q2 = np.array([_angles_pixel(P2, R2 @ (R @ x + T)) for x in X])
    assert np.abs(q1[:, 1] - q2[:, 1]).max() < 1e-9 * np.abs(q1[:, 1]).max()
    d = q1[:, 0] - q2[:, 0]
    assert (d > 0).all()
    # put each point on its own pixel: a 1 x n disparity map whose columns are the points' u (P shifted per point)
    out = []
    for (u, v), di in zip(q1, d):
        shift = np.array([[1.0, 0, -u], [0, 1.0, -v], [0, 0, 1.0]])
        out.append(np.asarray(reproject_spherical(np.array([[di]]), shift @ P1, shift @ P2))[0, 0])
    back = np.asarray(to_original_left(np.array(out), R1))
    assert np.abs(back - X).max() < 1e-9 * np.abs(X).max()
    pinhole = []
    for (u, v), di in zip(q1, d):
        shift = np.array([[1.0, 0, -u], [0, 1.0, -v], [0, 0, 1.0]])
        Q = np.asarray(rect.Q).copy()
        Q[0, 3], Q[1, 3] = Q[0, 3] + u, Q[1, 3] + v  # the same pixel through the paraxial Q
        pinhole.append(np.asarray(reproject_disparity(np.array([[di]]), Q))[0, 0])
    err = np.linalg.norm(np.asarray(to_original_left(np.array(pinhole), R1)) - X, axis=1) / np.linalg.norm(X, axis=1)
    assert np.nanmax(err) > 0.3


def test_the_maps_send_a_rectified_pixel_to_where_the_lens_images_its_point(rect):
    """lens_map of a spherical rectification against the fisheye projection of the scene point that pixel sees:
    the same pixel to 1e-6 px (both exact; rounding only)."""
    X = _scene_points()
    keep = np.degrees(np.arccos(X[:, 2] / np.linalg.norm(X, axis=1))) < 120.0  # inside the left lens's fold
    cams = WIDE.cameras()
    R, T = np.asarray(WIDE.R), np.asarray(WIDE.T).reshape(3)
    for cam, Rk, Pk, pts in ((cams[0], rect.R1, rect.P1, X[keep]), (cams[1], rect.R2, rect.P2, X[keep] @ R.T + T)):
        Rk, Pk = np.asarray(Rk), np.asarray(Pk)
        for x in pts[:40]:
            u, v = _angles_pixel(Pk, Rk @ x)
            shift = np.array([[1.0, 0, -u], [0, 1.0, -v], [0, 0, 1.0]])
            mx, my = lens_map(cam.k, cam.dist.coeffs, Rk, shift @ Pk, "fisheye", (1, 1), "spherical")
            q = np.asarray(fisheye.project(cam.k, cam.dist.coeffs[:4], x / np.linalg.norm(x)))
            assert abs(float(mx[0, 0]) - q[0]) < 1e-6 and abs(float(my[0, 0]) - q[1]) < 1e-6


def test_the_range_rate_is_the_derivative_of_the_range(rect):
    P1, P2 = np.asarray(rect.P1), np.asarray(rect.P2)
    d = np.stack([np.full(960, 5.0), np.full(960, 20.0), np.full(960, 60.0)])  # every column: psi -85..85 deg
    h = 1e-5
    r = lambda dd: np.linalg.norm(np.asarray(reproject_spherical(dd, P1, P2)), axis=-1)  # noqa: E731
    numeric = np.abs(r(d + h) - r(d - h)) / (2 * h)
    rate = np.asarray(spherical_range_rate(d, P1, P2))
    there = np.isfinite(r(d))
    assert there.mean() > 0.9 and np.array_equal(np.isfinite(rate), there)  # NaN where the point is not
    # central differences of a smooth function at step 1e-5 (away from the edge where the right ray passes 90 deg):
    # truncation ~h^2 r''' ~1e-10 relative, rounding ~eps r / h ~1e-11 relative: 1e-6 is far above both
    inner = there & np.isfinite(numeric)
    np.testing.assert_allclose(rate[inner], numeric[inner], rtol=1e-6)


def test_forcing_either_projection_and_the_refusals(rect):
    pin = rectify_any(WIDE, projection="pinhole")
    assert pin.projection == "pinhole" and "pinhole rectification as asked" in pin.why
    assert field_of_view(pin)["horizontal_deg"] < 2 * MAX_HALF_FIELD_DEG + 1e-6  # clamped, as before
    narrow = _calib(fisheye_rig())
    sph = rectify_any(narrow, projection="spherical")
    assert sph.projection == "spherical"
    maps = rectification_maps(narrow, sph)
    assert all(np.isfinite(m).any() for pair in maps for m in pair)
    with pytest.raises(DstereoError, match="rectification 'cylinder': use auto, pinhole or spherical"):
        rectify_any(WIDE, projection="cylinder")
    left, right = WIDE.cameras()
    from dstereo.models.rig import Rig

    vertical = Rig.from_matrix(np.eye(3), np.array([0.0, -100.0, 0.0]))
    with pytest.raises(DstereoError, match="baseline is vertical and the field too wide") as err:
        stereo_rectify_lenses(left, right, vertical, left.image_size, where="rig.yml")
    assert "\n" not in str(err.value) and "rig.yml" in str(err.value)


def test_two_views_that_share_no_field_are_refused_in_one_line():
    """Two 18-degree pinhole cameras looking 80 degrees apart (within MAX_AXES_DEG, so not refused as apart), forced
    spherical: the columns each sees (psi about -40 and +40 deg, +-9 wide) do not overlap."""
    from dstereo.models.pose import rodrigues

    K = np.array([[2000.0, 0, 320], [0, 2000, 240], [0, 0, 1]])
    R = np.asarray(rodrigues(np.array([0.0, np.radians(80.0), 0.0])))
    c = StereoCalibration(K, np.zeros(8), K, np.zeros(8), R, -R @ np.array([100.0, 0, 0]), (640, 480),
                          source="rig.yml")
    with pytest.raises(DstereoError, match="see no common field in front of the rig") as err:
        rectify_any(c, projection="spherical")
    assert "\n" not in str(err.value) and "rig.yml" in str(err.value)


def test_the_corners_reach_bounds_the_field_where_a_lens_has_no_ray_of_its_own():
    """stereo.yml's corner_angle_max1/2 (degrees): the spherical field stops there; the why names it. The cone of
    70 deg about the left axis (the rectified axis to within the rig's 0.7 deg half-rotation) spans at most
    2 x 70 deg in psi and in phi; the intersection with the right's 72 deg keeps the left's."""
    from dataclasses import replace

    reached = replace(WIDE, extras={"corner_angle_max1": 70.0, "corner_angle_max2": 72.0})
    rect = rectify_any(reached)
    assert "taken to where it ends, 70 deg off its axis (the corners' reach)" in rect.why
    fov = field_of_view(rect)
    assert 130.0 < fov["horizontal_deg"] <= 141.5 and 130.0 < fov["vertical_deg"] <= 141.5


def test_reproject_dispatches_on_the_projection(rect):
    matrices = {k: np.asarray(getattr(rect, k)) for k in ("P1", "P2", "Q")}
    d = np.full((3, 4), 30.0)
    spherical = np.asarray(reproject(d, matrices | {"projection": np.array("spherical")}))
    np.testing.assert_array_equal(spherical, np.asarray(reproject_spherical(d, matrices["P1"], matrices["P2"])))
    np.testing.assert_array_equal(np.asarray(reproject(d, matrices)), np.asarray(reproject_disparity(d, matrices["Q"])))


def test_points_beyond_infinity_are_nan(rect):
    P1, P2 = np.asarray(rect.P1), np.asarray(rect.P2)
    out = np.asarray(reproject_spherical(np.array([[0.0, -3.0, np.nan, 10.0]]), P1, P2))
    assert np.isnan(out[0, :3]).all() and np.isfinite(out[0, 3]).all()
