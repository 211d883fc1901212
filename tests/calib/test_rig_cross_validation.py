"""The rig cross-validation (calib/rig_cross_validation.py) on exact corners of ring rigs with Gaussian noise: a
right +- reads inside its band; the same run with every half's +- shrunk 2x (covariance / 4) reads outside it,
so a +- that shrinks fails the check. experiments/rig_cross_validation_seeds.py records 8 seeds of K = 2 and 3."""

import pytest

import dstereo.calib.multiview as multiview
from dstereo.calib.multiview import cameras_alone
from dstereo.calib.rig_cross_validation import cross_validate_rig
from dstereo.errors import DstereoError
from dstereo.synth.rig_corners import rig_corners


def _run(k, seed, splits=4):
    case = rig_corners(k, 32, seed, 0.1)
    cams = cameras_alone(case["obj"], case["obs"], case["visible"], case["image_sizes"])[0]
    return cross_validate_rig(case["obj"], case["obs"], case["visible"], case["image_sizes"], cams,
                              tuple(f"cam{c}" for c in range(k)), splits, seed=seed)


@pytest.mark.slow
@pytest.mark.parametrize("k,seed", [(2, 0), (3, 1)])
def test_a_right_uncertainty_reads_inside_its_band(k, seed):
    cv = _run(k, seed)
    assert cv.trusted, cv.line()
    lo, hi = cv.band(cv.rig_dof)
    assert lo <= cv.rig_ratio <= hi and len(cv.splits) == 4
    assert len(cv.as_dict()["per_split"]) == 4


@pytest.mark.slow
def test_a_shrunk_uncertainty_fails(monkeypatch):
    """Every half's covariance divided by 4 (its +- 2x optimistic): chi^2 / dof x 4, past the band's top (2.10
    for K = 2's 6 placement parameters) unless the right statistic were below 0.53; it measured 0.6-0.8."""
    solve = multiview.calibrate_views

    def optimistic(*args, **kwargs):
        sol = solve(*args, **kwargs)
        sol.cov = sol.cov / 4.0
        return sol

    monkeypatch.setattr(multiview, "calibrate_views", optimistic)
    cv = _run(2, 0)
    assert not cv.trusted and cv.rig_ratio > cv.band(cv.rig_dof)[1], cv.line()
    assert "optimistic" in cv.verdict()


def test_too_few_frames_to_halve_is_refused():
    case = rig_corners(2, 6, 0, 0.1)
    with pytest.raises(DstereoError, match="cannot be halved"):
        cross_validate_rig(case["obj"], case["obs"], case["visible"], case["image_sizes"], list(case["rig"].cameras),
                           ("a", "b"), 2)
