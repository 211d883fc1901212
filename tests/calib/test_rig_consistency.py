"""The rig-consistency test (calib/rig_consistency.py) on exact corners of ring rigs with Gaussian noise.

Under its hypothesis (simultaneous frames, a rigid rig, white corner noise) T/c follows F(c, dof_noise): mean 1,
standard deviation sqrt(2/c) ~ 0.1 for the c ~ 140-300 constraints of these rigs; the experiment
experiments/rig_consistency_seeds.py measured 0 of 60 seeds flagged and means 0.95-1.02 (K = 2, 3, 4).
"""

import numpy as np
import pytest

from dstereo.calib.multiview import calibrate_views, cameras_alone
from dstereo.calib.rig_consistency import of_multiview
from dstereo.synth.rig_corners import rig_corners


def _cameras(case):
    """Each camera calibrated alone on its own views, as `--cameras` starts the rig."""
    return cameras_alone(case["obj"], case["obs"], case["visible"], case["image_sizes"])[0]


def _consistency(case):
    joint = calibrate_views(case["obj"], case["obs"], case["visible"], case["image_sizes"], mode="joint",
                            cameras=_cameras(case))
    return of_multiview(joint, case["obj"], case["obs"])


SEEDS = (0, 1, 2, 3)


@pytest.mark.slow
@pytest.mark.parametrize("k", [2, 3])
def test_simultaneous_frames_read_one_on_average_and_are_not_flagged(k):
    ratios = []
    for seed in SEEDS:
        r = _consistency(rig_corners(k, 24, seed, 0.1))
        assert r.consistent, r.line()
        ratios.append(r.ratio)
    # the mean of 4 draws of F(c, .)/c has sd ~ 0.1 / 2 = 0.05: +-0.2 is 4 sd. A wrong count of the constraints
    # (a pose too many or too few per frame: c off by 6 F / c ~ 50-100 %) or a noise estimate without its degrees
    # of freedom moves it out.
    assert abs(np.mean(ratios) - 1.0) < 0.2, ratios


@pytest.mark.slow
@pytest.mark.parametrize("k", [2, 3])
def test_a_board_moved_between_the_exposures_is_flagged_on_every_seed(k):
    for seed in SEEDS:
        r = _consistency(rig_corners(k, 24, seed, 0.1, shift_mm=0.5))
        assert not r.consistent and r.ratio > 5, r.line()
        assert "not simultaneous" in r.warning() and r.excess_px > 0.1


def test_a_frame_taken_at_another_moment_is_named_first():
    """One frame whose right image came 2 mm of board motion later (a dropped trigger, a frame paired with its
    neighbour): the other 23 frames hold the rig, so that frame's own statistic stands out."""
    case = rig_corners(2, 24, 5, 0.1)
    late = rig_corners(2, 24, 5, 0.1, shift_mm=2.0)
    case["obs"][6, 1] = late["obs"][6, 1]
    r = _consistency(case)
    assert not r.consistent
    assert r.worst_frames(1)[0][0] == "frame 6", r.worst_frames(3)


def _rejecting(case, reject=True):
    from dstereo.jobs.calibrate_cameras import reject_inconsistent_frames

    n = len(case["obs"])
    inliers = np.broadcast_to(case["visible"][:, :, None], case["obs"].shape[:3]).copy()
    return reject_inconsistent_frames(case["obj"], case["obs"], case["visible"], case["image_sizes"], _cameras(case),
                                      ("c0", "c1", "c2")[:case["obs"].shape[1]], False, inliers, None,
                                      [f"f{i:02d}" for i in range(n)], reject)


@pytest.mark.slow
def test_a_frame_the_rig_cannot_explain_is_rejected_like_an_outlier_view(k=3):
    """One frame exposed 1 mm away by every camera but the reference (the others simultaneous): it is the frame
    removed, and the rig without it is consistent (measured: 17 of 18 seeds of K = 2, 3, 4 remove it, the 18th
    nothing, consistent). Simultaneous frames lose none (18 of 18); a rig whose every frame is off keeps its
    warning and every frame (removing frames does not make it consistent), and --no-outlier-rejection removes
    nothing."""
    from test_rig_subsets import _one_frame_moved

    clean = rig_corners(k, 24, 0, 0.1)
    bad = int(np.flatnonzero(clean["visible"].sum(1) >= 2)[3])
    rig = _rejecting(_one_frame_moved(k, 24, bad, 0, 1.0))
    assert [name for name, _ in rig.rejected] == [f"f{bad:02d}"] and rig.consistency.consistent, rig.rejected
    assert len(rig.frames) == 23 and rig.obs.shape[0] == 23 and rig.joint.poses.shape[0] == 23
    assert _rejecting(clean).rejected == []
    kept = _rejecting(_one_frame_moved(k, 24, bad, 0, 1.0), reject=False)
    assert kept.rejected == [] and not kept.consistency.consistent
    moved = _rejecting(rig_corners(k, 24, 1, 0.1, shift_mm=0.5))  # every frame off: none removed, still flagged
    assert not moved.consistency.consistent and moved.rejected == [] and len(moved.frames) == 24
