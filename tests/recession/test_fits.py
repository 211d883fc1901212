"""The recession line fits' intervals (dstereo/recession/fits.py) against the textbook and against their claim:
scipy.stats.linregress for the estimates and standard errors, the confidence band of a regression line
t(0.975, n - 2) s sqrt(1/n + (x0 - mean x)^2 / Sxx), and Monte Carlo coverage of the 95 % intervals (issue 32: the
band with 1.0 in place of the t quantile passed the suite)."""

import numpy as np
import pytest
from scipy import stats

from dstereo.recession.fits import line_band, line_fit, rate_map

T = np.array([0.0, 2.0, 3.5, 6.0, 8.0, 11.0])  # six frames, unevenly spaced: t(0.975, 4) = 2.78, far from 1


def _line(seed: int, sigma: float = 0.05) -> np.ndarray:
    return 0.3 + 0.021 * T + np.random.default_rng(seed).normal(0.0, sigma, len(T))


@pytest.mark.numerics
def test_rate_and_its_interval_are_linregress_and_students_t():
    r = _line(0)
    fit, ref = line_fit(T, r), stats.linregress(T, r)
    # two least-squares solutions of the same 6 x 2 system (normal equations here, linregress's closed-form
    # moments): a few roundings of O(1) values apart
    assert fit.rate == pytest.approx(ref.slope, rel=1e-12) and fit.intercept == pytest.approx(ref.intercept, abs=1e-12)
    assert fit.rate_se == pytest.approx(ref.stderr, rel=1e-10)
    half = stats.t.ppf(0.975, len(T) - 2) * ref.stderr
    assert fit.ci95 == pytest.approx((ref.slope - half, ref.slope + half), rel=1e-10)


@pytest.mark.numerics
def test_line_band_is_the_textbook_confidence_band_of_the_line():
    r = _line(1)
    fit, ref = line_fit(T, r), stats.linregress(T, r)
    at = np.array([-1.0, 0.0, 5.0, 11.0, 14.0])
    s = np.sqrt(np.sum((r - ref.intercept - ref.slope * T) ** 2) / (len(T) - 2))
    expected = stats.t.ppf(0.975, len(T) - 2) * s * np.sqrt(1 / len(T) + (at - T.mean()) ** 2
                                                             / np.sum((T - T.mean()) ** 2))
    # the same closed form from two fits of one line (agreeing to ~1e-15): residuals of 0.05 on values ~0.5 lose
    # ~10 ulps
    np.testing.assert_allclose(line_band(fit, T, r, at), expected, rtol=1e-10)
    assert line_band(line_fit(T[:2], r[:2]), T[:2], r[:2], at) is None  # no scatter estimable from two frames


def test_the_95_percent_intervals_cover_the_truth_95_percent_of_the_time():
    """2000 simulated sequences of six frames: the rate's interval and the line's band at three times hold the
    truth in 95 % of them. Binomial: 2000 draws at p = 0.95 scatter by 0.49 %; 0.93-0.97 is four of those. With
    z = 1 in place of t(0.975, 4) the coverage is ~63 %, with the normal 1.96 ~88 %."""
    at = np.array([0.0, 5.0, 14.0])
    truth_at = 0.3 + 0.021 * at
    rate_in, band_in = 0, np.zeros(len(at))
    n = 2000
    for seed in range(n):
        r = _line(seed + 100)
        fit = line_fit(T, r)
        rate_in += fit.ci95[0] <= 0.021 <= fit.ci95[1]
        band_in += np.abs(fit.intercept + fit.rate * at - truth_at) <= line_band(fit, T, r, at)
    assert 0.93 <= rate_in / n <= 0.97
    assert np.all((0.93 <= band_in / n) & (band_in / n <= 0.97)), band_in / n


@pytest.mark.numerics
def test_rate_map_cells_are_the_line_fit_of_their_frames():
    rng = np.random.default_rng(3)
    maps = 0.3 + 0.021 * T[:, None, None] + rng.normal(0.0, 0.05, (len(T), 2, 3))
    maps[1, 0, 0] = maps[4, 0, 0] = np.nan  # a cell that misses two frames: fitted on the other four
    maps[:, 1, 2] = np.nan
    maps[:4, 1, 2] = [0.1, 0.2, np.nan, 0.3]  # three frames: the minimum
    out = rate_map(T, maps)
    for iy in range(2):
        for ix in range(3):
            ok = np.isfinite(maps[:, iy, ix])
            fit = line_fit(T[ok], maps[ok, iy, ix])
            # the same least squares, one in closed-form moments per cell, one by normal equations: roundings apart
            assert out["rate"][iy, ix] == pytest.approx(fit.rate, rel=1e-10)
            assert out["ci95_half"][iy, ix] == pytest.approx(fit.ci95[1] - fit.rate, rel=1e-9)
            assert out["frames"][iy, ix] == ok.sum()
