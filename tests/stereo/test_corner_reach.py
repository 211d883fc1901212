"""`stereo.reconstruct.beyond_corner_reach`: the reconstructed points that lie farther off a camera's axis than its
calibration's corners reached (stereo.yml's corner_angle_max1/2), against angles computed by hand."""

import numpy as np

from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.stereo.reconstruct import beyond_corner_reach

def _calib(extras):
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    return StereoCalibration(K1=K, D1=np.zeros(5), K2=K, D2=np.zeros(5), R=np.eye(3), T=np.array([-100.0, 0, 0]),
                             image_size=(640, 480), extras=extras)

def test_points_beyond_each_cameras_reach_are_counted():
    """Right camera at x + 100 mm' = x - 100 (T = (-100, 0, 0)). Points (x, 0, 1000): x = 0 is 0 deg left, 5.7 right;
    x = 1000 is 45.0 deg left, atan(0.9) = 42.0 right; x = 1200 is 50.2 left, atan(1.1) = 47.7 right. Reach 30 deg
    left, 43 right: the last two beyond the left's, the last alone beyond the right's; NaN points are no points."""
    pts = np.array([[0.0, 0, 1000], [1000.0, 0, 1000], [1200.0, 0, 1000], [np.nan] * 3]).reshape(2, 2, 3)
    r = beyond_corner_reach(pts, _calib({"corner_angle_max1": 30.0, "corner_angle_max2": 43.0}))
    assert r == {"left_deg": 30.0, "right_deg": 43.0, "points": 3, "beyond_left": 2, "beyond_right": 1, "beyond": 2,
                 "beyond_share": 2 / 3}
    # one camera's reach alone: only it is checked
    r = beyond_corner_reach(pts, _calib({"corner_angle_max2": 43.0}))
    assert r["left_deg"] is None and "beyond_left" not in r and r["beyond"] == 1
    # reach beyond every point: none counted; no recorded reach, or no point: nothing to say
    assert beyond_corner_reach(pts, _calib({"corner_angle_max1": 60.0, "corner_angle_max2": 60.0}))["beyond"] == 0
    assert beyond_corner_reach(pts, _calib({})) is None
    assert beyond_corner_reach(np.full((2, 2, 3), np.nan), _calib({"corner_angle_max1": 30.0})) is None
