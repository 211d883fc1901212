"""Subsets whose solves did not converge are left out of a calibration's statistics (one camera and rig),
and a calibration none of whose subsets converged is refused. Real pairs: OpenCV's 13 sample pairs, m = 12."""

import dataclasses

import numpy as np
import pytest

from conftest import require_data
from dstereo.calib import mono
from dstereo.calib.calibrations import StereoSources
from dstereo.jobs.calibrate_stereo import calibrate_stereo_project
from dstereo.jobs.calibrate_camera import calibrate_camera
from dstereo.config.calibration import Config
from dstereo.errors import DstereoError
from dstereo.solver.lm import LMOptions

# final="mean": the written values are then the mean over the usable subsets, which is where averaging
# unconverged ones in would show (the default writes the solve on the surviving views instead).
CONFIG = Config(pattern=(9, 6), square=1.0, per_set=12, final="mean")
POISONED = [2, 7]  # 2 of the C(13, 12) = 13 subsets


def _poison(solutions, column: int, offset: float):
    """Subsets POISONED as an unconverged solve leaves them: status 'iteration limit', values far off."""
    values, status = solutions.values.copy(), solutions.status.copy()
    values[POISONED, column] += offset
    status[POISONED] = -1
    return dataclasses.replace(solutions, values=values, status=status)


def test_unconverged_subsets_are_left_out_of_the_final_values(monkeypatch):
    folder = require_data("opencv_stereo")
    real = mono.solve_subsets
    monkeypatch.setattr(mono, "solve_subsets", lambda *a, **k: _poison(real(*a, **k), 0, 50.0))  # fx + 50 px
    cal = calibrate_camera(folder, CONFIG.with_overrides(glob="left*.jpg"))
    assert cal.unconverged == POISONED
    assert any("2 of 13 subset solves did not converge" in w and "subsets 2, 7" in w for w in cal.warnings)
    kept = np.delete(cal.subsets.values, POISONED, axis=0)
    # No steps: the final values are the plain mean of the converged subsets (the same rows, summed by the same
    # numpy routine: equal to rounding). Averaging the poisoned two in would move fx by 100 / 13 = 7.7 px.
    for j, name in enumerate(cal.full.names):
        assert cal.final[name] == pytest.approx(kept[:, j].mean(), rel=1e-12), name


def test_a_calibration_with_no_converged_subset_is_refused(monkeypatch):
    """One LM iteration from the full set's optimum cannot meet ftol: every subset ends at the limit (-1)."""
    folder = require_data("opencv_stereo")
    real = mono.solve_subsets
    monkeypatch.setattr(mono, "solve_subsets", lambda *a, **k: real(*a, **{**k, "options": LMOptions(max_iter=1)}))
    with pytest.raises(DstereoError, match="none of the 13 subset solves converged"):
        calibrate_camera(folder, CONFIG.with_overrides(glob="left*.jpg"))


@pytest.mark.slow
def test_unconverged_rig_subsets_are_left_out_of_the_rig(monkeypatch):
    """A stereo rig (the K-camera job, K = 2): the rig's frame subsets whose solves did not converge are left out of
    the statistics the stereo steps and the survivors are computed from, with a warning."""
    from dstereo.calib import rig_subsets

    folder = require_data("opencv_stereo")
    left, right = sorted(folder.glob("left*.jpg")), sorted(folder.glob("right*.jpg"))
    sources = StereoSources(tuple(left), tuple(right), tuple(left), tuple(right), "test pairs")
    real = rig_subsets.solve_view_subsets
    # column 3: the right camera's Tx (after its RVx, RVy, RVz), moved by 1 square in the poisoned two
    monkeypatch.setattr(rig_subsets, "solve_view_subsets", lambda *a, **k: _poison(real(*a, **k), 3, 1.0))
    job = calibrate_stereo_project(sources, CONFIG.with_overrides(mode="stereo"))
    assert any("2 of 13 rig subset solves did not converge" in w for w in job.warnings), job.warnings
    f = job.subsets.filtering
    assert list(np.flatnonzero(~f.usable)) == POISONED
    alive = f.alive_after(len(f.steps))
    assert not alive[POISONED].any() and alive.sum() > 0
    # Tx moved by 1 square in the poisoned two: averaged in, Tx would move by 2 / 13 = 0.15 square.
    for name in ("Tx@left-right", "Tnorm@left-right", "RVx@left-right", "stereo_re@left-right"):
        column = f.column(name)
        assert job.subsets.stats()[name]["mean"] == pytest.approx(column[alive].mean(), rel=1e-12), name
