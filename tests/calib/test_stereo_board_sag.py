"""A stereo rig on a sagging board (issue 29): each camera solves the sag on its own views (the one-camera default),
the rig is solved on their inverse-variance mean (`stereo_pipeline.rig_board_sag`), held, as subsets hold it.

Exact corners of the K = 2 ring rig (synth/rig_corners.py) seeing a board that sags 0.3 mm along x, 0.1 px noise."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dstereo.calib.mono import calibrate_full
from dstereo.calib.stereo import calibrate_stereo
from dstereo.jobs.calibrate_stereo import rig_board_sag
from dstereo.models.camera import Camera
from dstereo.synth.rig_corners import rig_corners

SAG = (0.3, 0.0)


def _rig(seed, board_sag: bool, noise=0.1):
    case = rig_corners(2, 24, seed, noise, sag_mm=SAG)
    obj = case["obj"]
    cams, models = {}, []
    for side, c in (("left", 0), ("right", 1)):
        sol = calibrate_full(obj, case["obs"][:, c], case["image_sizes"][c], board_warp=board_sag)
        cams[side] = SimpleNamespace(full=sol, config=SimpleNamespace(unit="mm"))
        models.append(Camera.create(*map(float, sol.values[:4]), sol.coeffs, sol.free, case["image_sizes"][c]))
    det = SimpleNamespace(board=SimpleNamespace(object_points=lambda: obj), solved_board=None)
    warnings = []
    sag = rig_board_sag(det, cams, warnings) if board_sag else None
    board = obj if sag is None else det.solved_board
    rig = calibrate_stereo(board, case["obs"][:, 0], case["obs"][:, 1], *models, "fixed")
    truth = case["rig"].T_cam_ref[1]
    angle = np.degrees((Rotation.from_rotvec(rig.rvec).inv() * Rotation.from_rotvec(truth[:3])).magnitude())
    baseline = abs(rig.baseline / np.linalg.norm(truth[3:]) - 1.0)
    return SimpleNamespace(sag=sag, warnings=warnings, angle=angle, baseline=baseline, rig=rig,
                           focal=abs(models[0].k[0] / case["rig"].cameras[0].k[0] - 1.0))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_sag_the_rig_is_solved_on_is_within_its_sigma(seed):
    r = _rig(seed, board_sag=True)
    # within 10 % (issue 15's and 29's figure) and within 3.5 of its own sigma (the mean of two independent
    # cameras' estimates: its sigma is theirs combined)
    assert abs(r.sag.value[0] - SAG[0]) < 0.1 * SAG[0] and np.all(np.abs(r.sag.value - SAG) < 3.5 * r.sag.std)
    assert r.warnings == []  # both cameras measure one sag


def test_exact_corners_give_the_exact_rig_on_the_sagged_board_and_a_biased_one_on_the_flat():
    """Without noise the sagged board is the true board: sag, rig and lens to the solvers' rounding (the limits
    are far above the 1e-13 measured, far below the flat board's bias). The same corners on a
    flat board: the focal length, the rotation and the baseline are off by far more (measured 2.0 deg, 1.1 %, 2 %)."""
    sagged, flat = _rig(0, board_sag=True, noise=0.0), _rig(0, board_sag=False, noise=0.0)
    np.testing.assert_allclose(sagged.sag.value, SAG, atol=1e-6)
    assert sagged.angle < 1e-5 and sagged.baseline < 1e-7 and sagged.focal < 1e-7, vars(sagged)
    assert flat.angle > 0.05 and flat.baseline > 1e-3 and flat.focal > 1e-3, vars(flat)
