"""The camera file is a solution (issue 15, scope 1): the solve on the surviving views, the thesis's subset
mean beside it (and as `final = "mean"`), a warning when the mean fits visibly worse, and the rig's +- with the
intrinsics' errors carried into it (fixed mode).

Synthetic views of a 9 x 6 board (square 1) through a known 640 x 480 camera, 0.2 px noise; a few shapes only,
so the compiled programs are shared between the tests.
"""

from types import SimpleNamespace

import cv2
import jax
import numpy as np
import pytest

from conftest import require_data, run_cli
from dstereo.calib import mono
from dstereo.calib.final_solution import camera_final, surviving_views, view_survival
from dstereo.calib.robust_steps import run_steps
from dstereo.calib.subsets import plan_subsets
from dstereo.config.calibration import Step
from dstereo.models.camera import project_view

K = np.array([500.0, 500.0, 320.0, 240.0])
COEFFS = np.array([-0.3, 0.1, 0.001, -0.001, -0.02, 0, 0, 0])
SIZE = (640, 480)
FIVE = ("k1", "k2", "p1", "p2", "k3")
RATIONAL = FIVE + ("k4", "k5", "k6")
_project = jax.vmap(jax.vmap(project_view, in_axes=(None, None, None, 0)), in_axes=(None, None, 0, None))


def _board():
    g = np.mgrid[0:9, 0:6].T.reshape(-1, 2).astype(float)
    return np.c_[g, np.zeros(len(g))]


def _poses(seed, n):
    """Board poses aimed at points spread over the frame, tilted up to 40 degrees, 9-14 squares away."""
    rng, obj = np.random.default_rng(seed), _board()
    out = []
    for _ in range(n):
        rvec = np.deg2rad(rng.uniform(-40, 40, 3)) * np.array([1, 1, 0.3])
        aim = np.array([rng.uniform(150, 490), rng.uniform(110, 370)])
        ray = np.r_[(aim - K[2:]) / K[:2], 1.0]
        out.append(np.r_[rvec, rng.uniform(9, 14) * ray - cv2.Rodrigues(rvec)[0] @ obj.mean(axis=0)])
    return np.array(out)


def _views(seed, n, noise=0.2):
    rng = np.random.default_rng(seed + 1000)
    obj = _board()
    return obj, np.asarray(_project(K, COEFFS, _poses(seed, n), obj)) + rng.normal(0, noise, (n, len(obj), 2))


@pytest.fixture(scope="module")
def bad_view_run():
    """10 views, view 0 with 1.5 px noise; every subset of 4 views solved; step re <= 0.4 px (good subsets
    are at ~0.28 px, those holding view 0 above 0.6 px)."""
    obj, obs = _views(3, 10)
    obs[0] += np.random.default_rng(7).normal(0, 1.5, obs[0].shape)
    full = mono.calibrate_full(obj, obs, SIZE, FIVE)
    plan = plan_subsets(10, 4)
    sub = mono.solve_subsets(obj, obs, plan, full)
    columns = ("re",) + full.names
    table = np.column_stack([sub.rms, sub.values])
    filtering = run_steps(table, columns, [Step(("re",), (0.4,))], sub.status > 0)
    mean = {n: float(np.mean(table[filtering.survivors, j + 1])) for j, n in enumerate(full.names)}
    return obj, obs, full, plan, filtering, table, mean


def test_written_camera_is_a_fresh_solve_on_the_surviving_views(bad_view_run):
    obj, obs, full, plan, filtering, table, mean = bad_view_run
    # The surviving views, counted independently: every view of every surviving subset.
    expected = np.zeros(10, bool)
    for row in np.asarray(plan.index)[filtering.survivors]:
        expected[list(row)] = True
    assert not expected[0] and expected[1:].all()  # the construction: view 0 is in no surviving subset
    np.testing.assert_array_equal(surviving_views(filtering, plan, 10, block=7), expected)
    alive, usable = view_survival(filtering, plan, 10, block=7)
    rows = np.asarray(plan.index)
    assert alive.tolist() == [sum(v in r for r in rows[filtering.survivors]) for v in range(10)]
    assert usable.tolist() == [sum(v in r for r in rows[filtering.usable]) for v in range(10)]
    fs = camera_final("survivors", filtering, plan, obj, obs, full, SIZE, mean)
    fresh = mono.calibrate_full(obj, obs[1:], SIZE, FIVE, alone=True)  # the same program on the same data: equal
    np.testing.assert_array_equal(fs.solution.values, fresh.values)
    assert fs.final == fresh.as_dict()
    # The solve fits its views better than the full set (which holds the noisy view) does on them.
    assert fs.check.rms_solution == pytest.approx(fresh.rms, rel=1e-9)  # LM pose refit: converged optimum


def test_mean_option_is_the_thesis_mean(bad_view_run):
    obj, obs, full, plan, filtering, table, mean = bad_view_run
    fs = camera_final("mean", filtering, plan, obj, obs, full, SIZE, mean)
    alive = table[filtering.survivors]
    for j, name in enumerate(full.names):
        assert fs.final[name] == pytest.approx(alive[:, j + 1].mean(), rel=1e-12)
    assert "thesis" in fs.source(list(map(str, range(10))))


def _halves_final(seed, free):
    """Two real subsets, the disjoint halves (odd / even views) of 12, each solved; the thesis's mean of them."""
    obj, obs = _views(seed, 12)
    full = mono.calibrate_full(obj, obs, SIZE, free)
    index = np.array([np.arange(0, 12, 2), np.arange(1, 12, 2)])
    halves = [mono.calibrate_full(obj, obs[i], SIZE, free) for i in index]
    columns = ("re",) + full.names
    table = np.array([np.r_[h.rms, h.values] for h in halves])
    filtering = run_steps(table, columns, [])
    mean = dict(zip(full.names, table[:, 1:].mean(axis=0)))
    return obj, obs, full, index, filtering, mean


@pytest.mark.parametrize("free, seed, worse", [(FIVE, 3, False), (RATIONAL, 3, True)])
def test_warning_fires_when_the_mean_fits_clearly_worse(free, seed, worse):
    """Rational model, 6 views per half: the halves' k's run wild (mean k1 ~ 8e2, correlated with k2, k4-k6)
    and the mean of the two is no camera (1.21x the solve's RMS, measured; seeds 1-6 give 1.002-1.21x); the
    5-coefficient halves average benignly."""
    from dstereo.jobs.calibrate_camera import _final_solution

    obj, obs, full, index, filtering, mean = _halves_final(seed, free)
    warnings = []
    det = SimpleNamespace(object_points=obj, image_size=SIZE)
    fs = _final_solution(SimpleNamespace(final="survivors"), filtering, index, det, obs, full, mean, warnings)
    assert fs.solution is full  # every view survives: the full-set solve is the answer
    assert fs.check.mean_worse is worse
    if worse:
        assert fs.check.ratio > 1.1
        assert len(warnings) == 1 and f"{fs.check.rms_mean:.4f} px" in warnings[0] and \
            f"{fs.check.rms_solution:.4f} px" in warnings[0]
    else:
        assert fs.check.ratio < 1.005 and warnings == []


@pytest.mark.slow
def test_cli_final_mean_writes_the_thesis_mean(tmp_path):
    """`--final mean` reproduces the thesis's camera: camera.yml = the mean of subsets.csv's surviving rows."""
    import csv

    images = require_data("opencv_stereo")
    out = tmp_path / "r"
    code, _, err = run_cli("calibrate", "--images", images, "--glob", "left*.jpg", "--pattern", "9x6", "--per-set",
                           "11", "--step", "re=0.5", "--step", "fx=1.0,fy=1.0", "--final", "mean", "--out", out, "-q")
    assert code == 0, err
    rows = [r for r in csv.DictReader(open(out / "subsets.csv")) if r["survives"] == "1"]
    fs = cv2.FileStorage(str(out / "camera.yml"), cv2.FILE_STORAGE_READ)
    km, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
    fs.release()
    mean = lambda n: np.mean([float(r[n]) for r in rows])  # noqa: E731
    # CSV rows at 17 digits, averaged by np.mean in another order than the pipeline: ~10-term sums, rounding ~1e-15.
    np.testing.assert_allclose([km[0, 0], km[1, 1], km[0, 2], km[1, 2]],
                               [mean(n) for n in ("fx", "fy", "cx", "cy")], rtol=1e-12)
    np.testing.assert_allclose(dist, [mean(n) for n in FIVE[:2] + ("p1", "p2", "k3")], rtol=1e-12, atol=1e-15)


def test_final_option_in_toml_and_its_errors():
    from dstereo.config.calibration import Config, config_from_toml, to_toml, validate
    from dstereo.errors import DstereoError

    cfg = config_from_toml('[pattern]\ncolumns = 9\nrows = 6\n[calibration]\nfinal = "mean"\n', "t.toml")
    assert cfg.final == "mean" and Config().final == "survivors"
    assert config_from_toml(to_toml(cfg), "back.toml").final == "mean"  # the results folder's config.toml
    with pytest.raises(DstereoError, match="`final` 'median'; use one of survivors, mean"):
        validate(cfg.with_overrides(final="median"))


@pytest.mark.slow
def test_cli_stereo_final_mean_says_what_the_rig_holds(tmp_path):
    """Stereo with `--final mean` (issue 29: every rig runs the K-camera job, whose rig is the solve on the surviving
    frames): each camera's own camera.yml holds its subset mean (the thesis's answer), stereo.yml the joint rig on
    the surviving frames, the same numbers as cameras.yml, and the run says so."""
    import json

    from dstereo.io.calib_files import read_stereo_calibration

    data = require_data("opencv_stereo")
    out = tmp_path / "r"
    code, _, err = run_cli("calibrate", "--left", data / "left*.jpg", "--right", data / "right*.jpg", "--pattern",
                           "9x6", "--per-set", "12", "--final", "mean", "--out", out, "-q")
    assert code == 0, err
    assert "--final mean: each camera's file holds its subset mean" in err
    summary = json.loads((out / "cameras.json").read_text())
    back = read_stereo_calibration(out / "stereo.yml", unscaled=True)  # no --square: in board squares
    right = summary["cameras"][1]
    # stereo.yml and cameras.json: the same solve written by two writers (17 digits, a JSON float): exact
    np.testing.assert_allclose(back.T, right["T"], rtol=1e-12)
    np.testing.assert_allclose(back.K2, right["camera_matrix"], rtol=1e-12)
    # the rig subsets' files (C(13, 12) = 13 subsets), the thesis's statistics and its Figures 5.15/5.16
    rows = (out / "rig_subsets.csv").read_text().splitlines()
    assert len(rows) == 14 and "Tnorm@left-right" in rows[0] and "survives" in rows[0]
    assert (out / "rig_stats" / "step_0_initial.txt").is_file()
    for name in ("plots/T.png", "plots/RV.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"]({name})" in (out / "report.md").read_text()
    left_mean = json.loads((out / "left" / "summary.json").read_text())
    assert left_mean["final_source"].startswith("mean over the surviving subsets"), left_mean["final_source"]
