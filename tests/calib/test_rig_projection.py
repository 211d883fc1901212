"""A rig camera's projection uncertainty (calib/rig_projection.py): its programs compiled per bucket of frame counts
(runtime/buckets.py) give the unpadded figures. (Against mrcal: tests/io/test_cameramodel.py.)"""

import numpy as np
import pytest

from dstereo.calib.multiview import calibrate_views
from dstereo.calib.rig_projection import camera_poses, frames_covariance
from dstereo.models.distortion import PRESETS
from dstereo.runtime import buckets
from dstereo.synth.rig_corners import rig_corners

pytestmark = pytest.mark.slow  # see pyproject.toml: `make test` leaves these out, `make test-slow` runs them


def test_frames_padded_to_their_bucket_give_the_unpadded_covariance_and_poses(monkeypatch):
    """13 frames, computed as 14: the padded frame is unseen (its residuals 0) and its rows and columns are cut
    before J'J, so the same numbers come out (the same sums: equal to the last bit, measured; 1e-12 allowed)."""
    d = rig_corners(n_cameras=2, n_frames=13, seed=1, noise_px=0.2)
    sol = calibrate_views(d["obj"], d["obs"], d["visible"], d["image_sizes"], PRESETS["default"])
    out = {}
    for flag in ("0", "1"):
        monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", flag)
        cov, n, p = frames_covariance(sol, d["obj"], d["obs"])
        out[flag] = (cov, n, p, *camera_poses(sol, cov, 1)[1:])
    assert buckets.views(13) > 13
    (cov0, n0, p0, poses0, ck0), (cov1, n1, p1, poses1, ck1) = out["0"], out["1"]
    assert (n0, p0) == (n1, p1) and cov0.shape == cov1.shape == (p0, p0) and poses1.shape == (13, 6)
    np.testing.assert_allclose(cov1, cov0, rtol=1e-12, atol=1e-12 * np.abs(cov0).max())
    np.testing.assert_allclose(poses1, poses0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ck1, ck0, rtol=1e-12, atol=1e-12 * np.abs(ck0).max())
