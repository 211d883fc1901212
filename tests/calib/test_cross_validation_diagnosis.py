"""The cross-validation's diagnosis of an out-of-band prediction (`CrossValidation.diagnosis`): which lens parameters
differ beyond their +- and whether the excess lies inside the corners' field or where the model is extrapolated.
Each case plants a known excess and checks the figure against the definition (exact scalings)."""

import dataclasses

import numpy as np
import pytest

from dstereo.calib import cross_validation as cv
from dstereo.calib.mono import calibrate_full
from dstereo.synth.board_views import FREE, SIZE, scene


@pytest.fixture(scope="module")
def halves():
    cam, poses, obj, corners = scene(n_views=16, seed=0)
    obs = corners + np.random.default_rng(0).normal(0, 0.3, corners.shape)
    full = calibrate_full(obj, obs, SIZE, FREE)
    weights = np.zeros((2, len(obs)))
    weights[0, ::2], weights[1, 1::2] = 1.0, 1.0
    a, b = cv.solve_halves(full, obj, obs, weights)
    return full, obs, a, b


def _shrink(sol, index: int, factor: float):
    """The half's covariance with parameter `index`'s std divided by `factor` (row and column scaled)."""
    d = np.ones(len(sol.cov))
    d[index] = 1.0 / factor
    return dataclasses.replace(sol, cov=sol.cov * d[:, None] * d[None, :])


def test_a_parameter_claimed_too_tight_is_named_first(halves):
    """k1's std claimed 3x too small in both halves: its d^2 / (C_A + C_B)_ii grows 9x exactly (the others are
    unchanged to rounding), it leads the diagnosis and the optimistic verdict names it."""
    full, obs, a, b = halves
    names = cv._lens_names(full)
    corners = obs.reshape(-1, 2)
    fine = cv.compare_halves(a, b, names, SIZE, 1000.0, corners=corners)
    i = names.index("k1")
    bad = cv.compare_halves(_shrink(a, i, 3.0), _shrink(b, i, 3.0), names, SIZE, 1000.0, corners=corners)
    # the same program on inputs whose k1 row and column are scaled by 1/3: d^2 / var changes by a factor 9 and a
    # few roundings of the same operations (an ulp or so each); 1e-12 leaves thousands of ulps on any processor
    np.testing.assert_allclose(bad.parameter_excess[i], 9.0 * fine.parameter_excess[i], rtol=1e-12)
    others = np.arange(len(names)) != i
    np.testing.assert_allclose(bad.parameter_excess[others], fine.parameter_excess[others], rtol=1e-12)
    # planted well above every other parameter's figure (a right prediction's d^2/var is chi^2_1: here 9 x its own)
    xv = cv.CrossValidation([dataclasses.replace(bad, ratio=3.0)] * 4, 1000.0, [([0], [1])] * 4, np.zeros(2),
                            np.zeros(2), names=names)
    assert fine.parameter_excess[i] * 9.0 > fine.parameter_excess[others].max()  # (measured 20.6 against 6.4)
    assert next(iter(xv.diagnosis()["parameter_variance_ratio"])) == "k1"
    assert "differ most beyond their +- in k1" in xv.verdict()
    assert "can NOT be trusted" in xv.verdict() and "corners' field" in xv.verdict()


def test_an_excess_outside_the_corner_field_is_said_to_be_where_the_model_extrapolates(halves):
    """The split's differences tripled outside the corners' field: the pooled ratio there triples exactly (weights
    and predictions unchanged), inside it stays, and, the quotient outside / inside then lying above the band a
    right prediction's falls in (simulated from the halves' claimed uncertainty, over the same pixels), the verdict
    says the excess lies where the lens model is extrapolated and states that band. Unplanted (a right
    prediction's draw) and planted inside the field, it does not say so."""
    full, obs, a, b = halves
    names = cv._lens_names(full)
    s = cv.compare_halves(a, b, names, SIZE, 1000.0, corners=obs[:, :20].reshape(-1, 2))  # a partial field
    c = s.covered
    assert c.any() and (~c).any()
    parts = [(np.arange(0, len(obs), 2), np.arange(1, len(obs), 2))] * 4
    band = cv.band_if_right(parts, [a, b] * 4, [s] * 4)
    lo, hi = band.outside_over_inside
    assert lo < 1.0 < hi  # where a right prediction's quotient falls: around 1
    base = cv.CrossValidation([s] * 4, 1000.0, parts, np.zeros(2), np.zeros(2), names=names, band=band)
    d0 = base.diagnosis()
    assert d0["outside_over_inside_band_if_right"] == [lo, hi]
    # nothing planted: not above the band (the sentence is one-sided; this draw reads 0.84, below its lower end 0.86)
    assert d0["outside_over_inside"] <= hi and d0["extrapolation_excess"] is False
    for where, clause in ((~c, True), (c, False)):
        diff = s.diff.copy()
        diff[where] *= 3.0
        planted = dataclasses.replace(s, diff=diff, ratio=3.0)
        xv = cv.CrossValidation([planted] * 4, 1000.0, parts, np.zeros(2), np.zeros(2), names=names, band=band)
        d = xv.diagnosis()
        key = "ratio_pooled_outside_corner_field" if clause else "ratio_pooled_inside_corner_field"
        other = "ratio_pooled_inside_corner_field" if clause else "ratio_pooled_outside_corner_field"
        assert d[key] == pytest.approx(3.0 * d0[key], rel=1e-12)
        assert d[other] == pytest.approx(d0[other], rel=1e-12)
        assert d["extrapolation_excess"] is clause
        assert ("where the lens model is extrapolated" in xv.verdict()) is clause
        assert f"a right prediction {lo:.2f}-{hi:.2f} here" in xv.verdict()
        if clause:
            assert d0["outside_over_inside"] * 3.0 > hi  # so the planted case must say it
    # without a simulated band the tool cannot judge the quotient: no claim
    bare = cv.CrossValidation([dataclasses.replace(s, diff=s.diff * np.where(c, 1.0, 3.0)[..., None], ratio=3.0)] * 4,
                              1000.0, parts, np.zeros(2), np.zeros(2), names=names)
    assert bare.diagnosis()["extrapolation_excess"] is None
    assert "where the lens model is extrapolated" not in bare.verdict()


def test_the_quotient_band_holds_a_right_prediction(halves):
    """Differences drawn from the prediction itself (the halves' claimed uncertainty, as `band_if_right` draws
    them) fall above the quotient band's upper end in about 5 % of draws (its 95th percentile): over 400 fresh
    draws, between 1 % and 11 % (binomial, 400 draws: sd 1.1 %; 5 sd either side, floored)."""
    full, obs, a, b = halves
    names = cv._lens_names(full)
    s = cv.compare_halves(a, b, names, SIZE, 1000.0, corners=obs[:, :20].reshape(-1, 2))
    parts = [(np.arange(0, len(obs), 2), np.arange(1, len(obs), 2))]
    band = cv.band_if_right(parts, [a, b], [s], seed=0)
    z = np.random.default_rng(7).normal(size=(400, len(obs), a.score_roots.shape[1]))
    err = [np.einsum("vij,dvj->di", h.score_roots, z[:, part]) @ h.lens_gain.T for h, part in zip((a, b), parts[0])]
    *_, (n_in, n_out) = s.projection.simulate(*err, pooled=True)
    q = np.sqrt(n_out / s.projection.pooled(~s.covered)[1]) / np.sqrt(n_in / s.projection.pooled(s.covered)[1])
    assert 0.01 <= np.mean(q > band.outside_over_inside[1]) <= 0.11
