"""Cross-validation over random half splits: on a synthetic camera with independent corner noise (the premise of
the covariance) the prediction holds; a covariance 3x too optimistic is flagged; too few views is refused."""

import dataclasses

import numpy as np
import pytest

from dstereo.calib import cross_validation as cv
from dstereo.calib.mono import calibrate_full
from dstereo.errors import DstereoError
from dstereo.synth.board_views import FREE, SIZE, scene


@pytest.fixture(scope="module")
def honest():
    cam, poses, obj, corners = scene(n_views=16, seed=0)
    obs = corners + np.random.default_rng(0).normal(0, 0.3, corners.shape)
    full = calibrate_full(obj, obs, SIZE, FREE)
    return full, obj, obs, cv.cross_validate(full, obj, obs, SIZE, splits=6, seed=0)


def test_honest_noise_passes_cross_validation(honest):
    *_, xv = honest
    print("\n" + xv.verdict(), [round(s.ratio, 2) for s in xv.splits])
    assert len(xv.splits) == 6 and all(len(a) == len(b) == 8 and not set(a) & set(b) for a, b in xv.halves)
    assert xv.trusted and "can be trusted" in xv.verdict()
    # median of sqrt(chi^2_2) is 1.18; 6 splits x 192 correlated pixels pin it to about +-0.3 (seeds 0, 1: 1.34, 1.20)
    assert abs(xv.mahalanobis_median - cv.MAHALANOBIS_PERFECT) < 0.35


def test_optimistic_covariance_is_flagged(honest):
    full, obj, obs, _ = honest
    weights = np.zeros((2, len(obs)))
    weights[0, ::2], weights[1, 1::2] = 1.0, 1.0
    a, b = cv.solve_halves(full, obj, obs, weights)
    fine = cv.compare_halves(a, b, full.names, SIZE, 1000.0)
    shrink = lambda s: dataclasses.replace(s, cov=s.cov / 9.0)  # noqa: E731  (stds 3x too small)
    bad = cv.compare_halves(shrink(a), shrink(b), full.names, SIZE, 1000.0)
    np.testing.assert_allclose(bad.ratio, 3.0 * fine.ratio, rtol=1e-9)  # the ratio scales as 1/std exactly
    xv = cv.CrossValidation([bad] * 4, 1000.0, [([0], [1])] * 4, np.zeros(2), np.zeros(2))
    assert not xv.trusted and "can NOT be trusted" in xv.verdict() and "optimistic" in xv.verdict()


def test_too_few_views_is_refused(honest):
    full, obj, obs, _ = honest
    with pytest.raises(DstereoError, match="at least 8"):
        cv.cross_validate(full, obj, obs[:7], SIZE)


@pytest.mark.slow
def test_calibrate_cross_validate_writes_verdict_map_and_method(tmp_path):
    from conftest import require_data, run_cli

    data = require_data("opencv_stereo")  # skips with its reason when ../shared/data is absent
    out = tmp_path / "xv"
    code, _, err = run_cli("calibrate", "--images", data, "--glob", "left*.jpg", "--pattern", "9x6",
                           "--cross-validate", "4", "--out", out, "-q")
    assert code == 0, err
    import json

    s = json.loads((out / "summary.json").read_text())
    x = s["cross_validation"]
    assert x["splits"] == 4 and len(x["ratios"]) == 4 and isinstance(x["trusted"], bool)
    assert s["projection_uncertainty"]["method"] == "pose-compensated"
    assert (out / "plots" / "cross_validation.png").stat().st_size > 1000
    assert x["verdict"] in (out / "report.md").read_text()
    if not x["trusted"]:  # an uncertainty that fails the acceptance is said on stderr too, with its figures
        assert ("can NOT be trusted" in err) != ("the test cannot tell here" in err)
        assert ("cannot tell" in x["verdict"]) == bool(x["consistent_with_right_prediction"])
    # the split's halves are written as camera folders: `dstereo diff` on them reads the split's figures, the same
    # computation on the same numbers (camera.yml's 16 digits and the covariance file's float64: 1e-9)
    split = out / "cross_validation" / "split_1"
    code, _, err = run_cli("diff", split / "a", split / "b", "--out", tmp_path / "diff")
    assert code == 0, err
    d = json.loads((tmp_path / "diff" / "diff.json").read_text())["prediction"]
    assert d["ratio"] == pytest.approx(x["ratios"][0], rel=1e-9)
    assert d["mahalanobis_median"] == pytest.approx(x["mahalanobis_medians"][0], rel=1e-9)
    code, _, err = run_cli("calibrate", "--images", data, "--glob", "left*.jpg", "--pattern", "9x6",
                           "--projection-method", "mrcal", "--out", tmp_path / "bad")
    assert code == 1 and "--projection-method mrcal" in err and not (tmp_path / "bad").exists()


def test_parameters_differing_beyond_their_prediction_are_named_even_when_the_projection_passes(honest):
    """d'C^-1 d / G scales as 1/c for a covariance c times too small (exactly); a trusted projection whose
    parameters differ beyond PARAMETER_CHI2_MAX says that their +- cannot be read (cancelling parameters)."""
    *_, xv = honest
    assert xv.parameter_chi2 < cv.PARAMETER_CHI2_MAX and "cannot" not in xv.verdict()
    scaled = [dataclasses.replace(s, parameter_chi2=s.parameter_chi2 * 10.0 / xv.parameter_chi2) for s in xv.splits]
    odd = dataclasses.replace(xv, splits=scaled)
    assert odd.trusted and "single parameters' +- cannot" in odd.verdict()


def test_parameter_chi2_scales_with_the_covariance(honest):
    full, obj, obs, _ = honest
    weights = np.zeros((2, len(obs)))
    weights[0, ::2], weights[1, 1::2] = 1.0, 1.0
    a, b = cv.solve_halves(full, obj, obs, weights)
    fine = cv.compare_halves(a, b, full.names, SIZE, 1000.0)
    shrink = lambda s: dataclasses.replace(s, cov=s.cov / 9.0)  # noqa: E731
    bad = cv.compare_halves(shrink(a), shrink(b), full.names, SIZE, 1000.0)
    # the same scaled inverse of a matrix scaled by 1/9 (Jacobi scaling removes the factor): 9x to rounding
    np.testing.assert_allclose(bad.parameter_chi2, 9.0 * fine.parameter_chi2, rtol=1e-9)


def test_expected_log_ratio_equals_the_chi_square_closed_form_and_a_monte_carlo():
    """k equal eigenvalues: sum lambda z^2 / sum lambda = chi^2_k / k, E ln = psi(k/2) + ln(2/k) (closed form); the
    quadrature's error is below 1e-12 there (measured 1e-13). Unequal eigenvalues against 200,000 draws: the
    log's standard deviation is at most ~1.1 (one mode), so its mean is known to 0.0025; 0.01 is 4 standard errors."""
    from scipy.special import digamma

    for k in (1, 2, 3, 9, 40):
        assert cv.expected_log_ratio(np.full(k, 2.5)) == pytest.approx(0.5 * (digamma(k / 2) + np.log(2 / k)),
                                                                      abs=1e-12)
    rng = np.random.default_rng(3)
    lam = rng.exponential(size=6) ** 3
    z = rng.normal(size=(200_000, 6))
    mc = float(np.mean(0.5 * np.log((z ** 2 @ lam) / lam.sum())))
    assert cv.expected_log_ratio(np.r_[lam, 0.0, -1e-18]) == pytest.approx(mc, abs=0.01)  # zeros/rounding ignored


def test_a_right_prediction_reads_one_in_the_simulated_band(honest):
    """The band simulates the procedure with each half's own claimed uncertainty: by construction its ratio's
    median is 1 and its Mahalanobis median 1.18 (sqrt(chi^2_2)), up to the simulation's noise (400 draws of a
    6-split geometric mean whose log has sd ~0.35: the median to ~0.02 in the log) and the skew of a log of
    few chi-squares (the median of a mean of 6 such logs sits a few % above their mean): 0.15 and 0.1 allowed."""
    *_, xv = honest
    b = xv.band
    assert b is not None and b.draws == cv.NULL_DRAWS
    assert b.ratio_median == pytest.approx(1.0, abs=0.15)
    assert b.mahalanobis_median == pytest.approx(cv.MAHALANOBIS_PERFECT, abs=0.1)
    assert b.ratio[0] < 1.0 < b.ratio[1] and b.mahalanobis[0] < cv.MAHALANOBIS_PERFECT < b.mahalanobis[1]
    assert xv.consistent and all(s.modes >= 1.0 for s in xv.splits)
    # each split's ratio is its raw one divided by the typical value of a right prediction (below 1)
    for s in xv.splits:
        assert 0.5 < s.ratio_raw / s.ratio < 1.0


@pytest.mark.parametrize("factor", [3.0, 2.0])
def test_the_band_moves_with_the_claimed_uncertainty(honest, factor):
    """Halves claiming stds 3x (2x) too small, so their maps 3x (2x) too small inside the corners' fields where the
    statistic is taken: the observed ratio grows 3x (2x) exactly, the band stays where a right prediction is (it
    is simulated from what the halves claim, against what they claim, over the same pixels), so the ratio leaves
    the band above and the verdict is 'optimistic', not 'cannot tell' (2x: the band's upper end is below 2x this
    honest split's ratio, asserted first)."""
    full, obj, obs, xv = honest
    shrink = lambda s, h: dataclasses.replace(  # noqa: E731
        s, cov=s.cov / factor ** 2, score_roots=s.score_roots / factor, field=h.field)
    weights = np.zeros((2 * len(xv.halves), len(obs)))
    for i, (a, b) in enumerate(xv.halves):
        weights[2 * i, a], weights[2 * i + 1, b] = 1.0, 1.0
    sols = [shrink(s, h) for s, h in zip(cv.solve_halves(full, obj, obs, weights), xv.solutions)]
    splits = [cv.compare_halves(sols[2 * i], sols[2 * i + 1], full.names, SIZE, xv.range_)
              for i in range(len(xv.halves))]
    assert all(s.covered is not None and s.covered.any() and (s.covered == x.covered).all()
               for s, x in zip(splits, xv.splits))
    np.testing.assert_allclose([s.ratio for s in splits], [factor * s.ratio for s in xv.splits], rtol=1e-6)
    band = cv.band_if_right(xv.halves, sols, splits)
    assert band.ratio_median == pytest.approx(xv.band.ratio_median, rel=1e-9)  # same draws, scale-free
    assert factor * xv.ratio > xv.band.ratio[1]
    bad = dataclasses.replace(xv, splits=splits, band=band)
    assert not bad.consistent and bad.ratio > band.ratio[1] and "optimistic" in bad.verdict()


def test_a_half_that_leaves_a_pose_undetermined_is_refused_not_a_traceback(honest):
    """Without outlier rejection, fisheye640's rational model left a half with a singular pose block (measured):
    that half counts as not converged (cross_validate then refuses in one DstereoError), instead of LinAlgError."""
    full, obj, obs, _ = honest
    normal = np.asarray(full.normal)
    g = len(full.values)
    assert cv._poses_determined(normal, g)
    broken = normal.copy()
    broken[3, g: g + 6, g: g + 6] = 0.0  # a view whose board the model cannot place
    broken[3, g + 5, g + 5] = 1.0
    assert not cv._poses_determined(broken, g)
    nan = normal.copy()
    nan[0, 0, 0] = np.nan
    assert not cv._poses_determined(nan, g)


def test_the_verdict_reads_the_band_a_right_prediction_falls_in(honest):
    """Four cases of the same splits with a made-up band (the verdict's logic alone): inside both bands, trusted;
    inside the acceptance band but above this one, 'leans optimistic'; below the acceptance band but inside this
    one, 'cannot tell'; below both, pessimistic with its own cause (not the causes of optimism)."""
    *_, xv = honest
    band = lambda lo, hi: cv.BandIfRight((lo, hi), (0.0, 10.0), 1.0, 1.18, 0.9, 10)  # noqa: E731
    r = xv.ratio
    assert cv.RATIO_BAND[0] <= r <= cv.RATIO_BAND[1] and xv.mahalanobis_median <= cv.MAHALANOBIS_MAX
    assert "can be trusted" in dataclasses.replace(xv, band=band(r / 2, r * 2)).verdict()
    assert "leans optimistic" in dataclasses.replace(xv, band=band(r / 3, r / 1.5)).verdict()
    low = [dataclasses.replace(s, ratio=s.ratio * 0.5 / r) for s in xv.splits]  # geometric mean 0.5
    assert "cannot tell" in dataclasses.replace(xv, splits=low, band=band(0.3, 1.5)).verdict()
    text = dataclasses.replace(xv, splits=low, band=band(0.8, 1.5)).verdict()
    assert "NOT be trusted, it is pessimistic" in text and "outlier corners" not in text
