"""`uncertainty.camera_diff`: the projection difference of two cameras with the implied transform fitted, and its
first-order prediction. Checked against: zero for equal cameras (every lens model), the model's own projection
for the ray, central differences of the whole fitted difference for the prediction's linearisation (weighted and
not), the exact 1/std scaling of the ratio, and a Monte Carlo in parameter space (a right covariance reads 1, in
its band; a planted covariance 4x too small fails it)."""

import dataclasses

import numpy as np
import pytest

from dstereo.calib.mono import calibrate_full
from dstereo.uncertainty import camera_diff as cd
from dstereo.synth.board_views import FREE, SIZE, scene

GRID = (12, 9)  # small: every test here shares one compiled program per lens model


@pytest.fixture(scope="module")
def calibrated():
    """A synthetic camera calibrated from 12 views with 0.3 px noise: its values, covariance, joint and poses."""
    from dstereo.calib.finished import lens_covariance

    _, _, obj, corners = scene(n_views=12, seed=0)
    obs = corners + np.random.default_rng(0).normal(0, 0.3, corners.shape)
    full = calibrate_full(obj, obs, SIZE, FREE)
    lc = lens_covariance(full)
    params = np.concatenate([full.values[:4], full.camera().coeffs()])
    return cd.LensCamera("pinhole", params, lc.names, lc.cov, SIZE, "A", joint=lc.joint, poses=lc.poses)


def _perturbed(cam, delta):
    p = cam.params.copy()
    p[list(cam.index)] += delta
    return dataclasses.replace(cam, params=p)


@pytest.mark.parametrize("model", ["pinhole", "fisheye", "splined:6x5"])
def test_equal_cameras_differ_by_nothing_after_the_fit(calibrated, model):
    """Every lens model: a camera against itself differs by 0 (the rays are the model's own inverse, so each
    pixel's point projects back onto it, and the fit stays at the identity); at an infinite range the
    transform is a rotation alone."""
    if model == "pinhole":
        cam = calibrated
    elif model == "fisheye":
        cam = cd.LensCamera(model, np.r_[300.0, 301.0, 320.0, 240.0, 0.05, -0.01, 0.002, -0.0005, np.zeros(4)],
                            image_size=SIZE)
    else:
        knots = np.random.default_rng(1).normal(0, 0.5, 2 * 6 * 5)
        cam = cd.LensCamera(model, np.r_[330.0, 331.0, 320.0, 240.0, knots], image_size=SIZE)
    d = cd.projection_diff(cam, cam, 500.0, GRID)
    assert d.ok.mean() > 0.9 and np.nanmax(np.abs(d.diff)) < 1e-9 and np.max(np.abs(d.transform)) < 1e-9
    if model == "pinhole":
        inf = cd.projection_diff(cam, cam, np.inf, GRID)
        assert np.nanmax(np.abs(inf.diff)) < 1e-9 and np.all(inf.transform[3:] == 0.0)
        assert inf.weighting.startswith("uniform")  # no pose-compensated map at infinity


@pytest.mark.parametrize("weighted", [False, True])
def test_the_prediction_is_the_derivative_of_the_fitted_difference(calibrated, weighted):
    """e(h) = difference of A and A + h delta, the transform refitted each time: (e(h) - e(-h)) / 2h equals the
    prediction's linear map P F_B delta (P: what the fit absorbs removed), to the central difference's O(h^2)
    (h = 1e-3 of each parameter's std: measured 1e-9 relative, 1e-6 allowed)."""
    cam = calibrated
    std = np.sqrt(np.diag(cam.cov))
    delta = std * np.random.default_rng(5).normal(size=len(std))
    h = 1e-3
    d0 = cd.projection_diff(cam, cam, 600.0, GRID, weighted=weighted)
    plus = cd.projection_diff(cam, _perturbed(cam, h * delta), 600.0, GRID, weighted=weighted)
    minus = cd.projection_diff(cam, _perturbed(cam, -h * delta), 600.0, GRID, weighted=weighted)
    assert d0.weighting == ("pose-compensated maps" if weighted else "uniform")
    fd = ((plus.diff - minus.diff) / (2 * h))[d0.ok].ravel()
    lin = (d0.pf_b @ delta) / d0.root_w
    np.testing.assert_allclose(fd, lin, rtol=1e-6, atol=1e-6 * np.max(np.abs(lin)))
    if weighted:  # each pixel weighs 1 / (trace C_A + trace C_B) of the two maps, up to one constant
        prod = (d0.weight * d0.map_trace)[d0.ok]
        # weight = c / trace and weight * trace = c: one division and one product, a few ulps on any processor
        np.testing.assert_allclose(prod, prod[0], rtol=1e-12)
        assert np.ptp(d0.weight[d0.ok]) > 1.0  # and they do vary over the image


def test_the_ratio_scales_as_one_over_the_claimed_std(calibrated):
    """A covariance 9x smaller (stds 3x) triples the ratio exactly and leaves the band (a property of the
    prediction's shape, not its scale) unchanged; the weights come from the joint covariance, held."""
    other = _perturbed(calibrated, np.sqrt(np.diag(calibrated.cov)) * 0.7)
    fine = cd.projection_diff(calibrated, other, 600.0, GRID)
    small = lambda c: dataclasses.replace(c, cov=c.cov / 9.0)  # noqa: E731
    bad = cd.projection_diff(small(calibrated), small(other), 600.0, GRID)
    assert bad.ratio == pytest.approx(3.0 * fine.ratio, rel=1e-9)
    assert bad.band()["ratio"] == pytest.approx(fine.band()["ratio"], rel=1e-9)


def test_a_monte_carlo_of_right_covariances_reads_one_and_a_planted_wrong_scale_fails(calibrated):
    """Both cameras drawn around one truth with the covariance they claim: the log-ratio has mean 0 (60 draws of
    sd ~0.45: the geometric mean within exp(+-0.2), 3.4 standard errors) and ~90 % of draws fall in each draw's
    own 5-95 % band (binomial sd 4 %: at least 75 %), and so do their median Mahalanobis distances. Claiming stds
    2x too small (a planted wrong covariance scale, the truth's draws unchanged): the geometric mean doubles
    (outside exp(+-0.2)) and most draws leave the band."""
    cam = calibrated
    root = np.linalg.cholesky(cam.cov)
    rng = np.random.default_rng(11)
    logs, inside, logs_bad, inside_bad, inside_maha, diffs, traces = [], [], [], [], [], [], []
    for _ in range(60):
        a = _perturbed(cam, root @ rng.normal(size=len(root)))
        b = _perturbed(cam, root @ rng.normal(size=len(root)))
        d = cd.projection_diff(a, b, 600.0, GRID)
        diffs.append(d.diff)
        traces.append(np.trace(d.cov, axis1=-2, axis2=-1))
        logs.append(np.log(d.ratio))
        band = d.band(draws=1000)
        inside.append(band["ratio"][0] <= d.ratio <= band["ratio"][1])
        lo, hi = band["mahalanobis_median"]
        inside_maha.append(lo <= d.mahalanobis_median <= hi)
        bad = cd.projection_diff(dataclasses.replace(a, cov=a.cov / 4), dataclasses.replace(b, cov=b.cov / 4),
                                 600.0, GRID)
        logs_bad.append(np.log(bad.ratio))
        lo, hi = bad.band(draws=1000)["ratio"]
        inside_bad.append(lo <= bad.ratio <= hi)
    print(f"\nright: geometric mean {np.exp(np.mean(logs)):.3f}, inside its band {np.mean(inside):.2f}; "
          f"stds claimed 2x too small: {np.exp(np.mean(logs_bad)):.3f}, inside {np.mean(inside_bad):.2f}")
    assert abs(np.mean(logs)) < 0.2 and np.mean(inside) >= 0.75
    assert np.mean(inside_maha) >= 0.75  # the observed Mahalanobis median is computed as the simulated ones
    # each pixel's predicted 2 x 2 covariance (of the unweighted difference) against the draws' own spread: 60
    # draws give a trace to ~18 %; at the pixels of the smallest and the largest fit weight (14x apart here) too
    spread = np.mean(np.sum(np.array(diffs) ** 2, axis=-1), axis=0) / np.mean(traces, axis=0)
    w = d.weight
    ends = [spread[np.unravel_index(np.argmin(np.where(d.ok, w, np.inf)), w.shape)],
            spread[np.unravel_index(np.argmax(w), w.shape)]]
    print(f"observed / predicted variance per pixel: median {np.median(spread[d.ok]):.2f}, at the least and the "
          f"most weighted pixel {ends[0]:.2f}, {ends[1]:.2f}")
    assert 0.75 < np.median(spread[d.ok]) < 1.33 and all(0.5 < x < 2.0 for x in ends)
    assert np.mean(logs_bad) > np.log(2.0) - 0.2 and np.mean(inside_bad) < 0.75


def test_one_dominant_mode_reads_one_after_its_typical_value(calibrated):
    """Only k1 uncertain: the difference has one mode, a right raw ratio is |z| for one normal z, typically
    exp(E ln|z|) = exp((psi(1/2) + ln 2) / 2) = 0.53. Divided by it, 60 draws' geometric mean reads 1 (log sd 1.1:
    within exp(+-0.45), 3.2 standard errors), the raw one near 0.53 (outside that)."""
    k1 = calibrated.names.index("k1")
    cov = np.zeros_like(calibrated.cov)
    cov[k1, k1] = calibrated.cov[k1, k1]
    cam = dataclasses.replace(calibrated, cov=cov)
    rng = np.random.default_rng(4)
    ratio, raw = [], []
    for _ in range(60):
        delta = np.zeros(len(cov))
        a = _perturbed(cam, np.where(np.arange(len(cov)) == k1, np.sqrt(cov[k1, k1]) * rng.normal(), 0.0))
        b = _perturbed(cam, np.where(np.arange(len(cov)) == k1, np.sqrt(cov[k1, k1]) * rng.normal(), 0.0))
        d = cd.projection_diff(a, b, 600.0, GRID)
        # A's and B's k1 act along nearly one direction (their Jacobians at two nearby cameras): one mode, nearly
        assert d.modes < 1.05 and d.typical == pytest.approx(0.530, abs=0.01)
        ratio.append(d.ratio)
        raw.append(d.ratio_raw)
        del delta
    assert abs(np.mean(np.log(ratio))) < 0.45 and abs(np.mean(np.log(raw)) - np.log(0.53)) < 0.45
    assert np.mean(np.log(raw)) < -0.45


def test_expected_log_ratio_is_the_one_cross_validation_uses():
    from dstereo.calib import cross_validation as cv

    assert cv.expected_log_ratio is cd.expected_log_ratio


@pytest.mark.slow
def test_two_calibrations_of_one_rendered_camera_read_inside_the_band_of_a_right_prediction():
    """The synthetic webcam rendered in two independent sets of 10 views (poses and sensor noise from their own
    seeds), detected and calibrated as `dstereo calibrate` solves a full set, twice over (2 pairs): the geometric
    mean of the pairs' ratios lies inside the 5-95 % band that right predictions' geometric means fall in
    (simulated from the pairs' own covariances). The same pairs claiming stds 3x too small (a planted wrong
    covariance scale: the ratios triple exactly) fall outside it. experiments/diff_rendered.py runs 20 pairs."""
    from dstereo.calib.finished import lens_covariance
    from dstereo.synth.board_views import rendered_views, webcam
    from dstereo.uncertainty.projection import mean_board_distance

    cam = webcam()

    def calibrated_camera(seed):
        obj, obs = rendered_views(cam, 10, seed)
        sol = calibrate_full(obj, obs, cam.image_size, FREE)
        lc = lens_covariance(sol)
        return (cd.LensCamera("pinhole", np.concatenate([sol.values[:4], sol.camera().coeffs()]), lc.names, lc.cov,
                              cam.image_size, joint=lc.joint, poses=lc.poses), mean_board_distance(sol.poses, obj))

    diffs = []
    for pair in range(2):
        (a, range_), (b, _) = calibrated_camera(10 + 2 * pair), calibrated_camera(11 + 2 * pair)
        diffs.append(cd.projection_diff(a, b, range_, GRID))
    rng = np.random.default_rng(0)
    sims = [d.simulate(rng.normal(size=(2000, d.root_a.shape[1])) @ d.root_a.T,
                       rng.normal(size=(2000, d.root_b.shape[1])) @ d.root_b.T)[0] for d in diffs]
    band = np.percentile(np.exp(np.mean(np.log(sims), axis=0)), [5, 95])
    gm = float(np.exp(np.mean(np.log([d.ratio for d in diffs]))))
    print(f"\nrendered pairs: ratios {[round(d.ratio, 3) for d in diffs]}, geometric mean {gm:.3f}, band of a right "
          f"prediction {band.round(3)}")
    assert band[0] <= gm <= band[1]
    assert not band[0] <= 3.0 * gm <= band[1]  # stds claimed 3x too small: every ratio triples (scaling test above)


def test_the_corner_field_is_the_grid_pixels_within_its_reach():
    """`corner_field` against its definition on a hand-made case: one corner at (100, 50) on a 10 px grid marks
    exactly the pixels strictly closer than the reach, by default 1.5 grid steps = 15 px (|d|^2 < 225: (100, 50) +-
    (10, 10) is in, +- 20 on one axis out; 30 px given: +- (20, 20) in, +- 30 out); NaN corners are ignored, and no
    corner marks nothing."""
    u, v = np.arange(0.0, 200.0, 10.0), np.arange(0.0, 120.0, 10.0)
    uu, vv = np.meshgrid(u, v)
    corners = np.array([[100.0, 50.0], [np.nan, np.nan]])
    for reach, inside in ((None, 225.0), (30.0, 900.0)):
        f = cd.corner_field(u, v, corners, reach)
        np.testing.assert_array_equal(f, (uu - 100.0) ** 2 + (vv - 50.0) ** 2 < inside)
    f = cd.corner_field(u, v, corners)
    assert f[vv == 60.0][uu[vv == 60.0] == 110.0].all() and not f[vv == 50.0][uu[vv == 50.0] == 120.0].any()
    assert not cd.corner_field(u, v, np.full((3, 2), np.nan)).any()


@pytest.mark.parametrize("scale", [0.5, 2.0, 3.0])
def test_the_corner_field_of_the_same_views_at_another_resolution_is_the_same(scale):
    """The field is where the views measured the lens, whatever the pixel size: the same corners on an image
    `scale` times larger, on its own grid (`grid_pixels`, GRID), mark the same grid pixels (a reach in pixels
    did not: at 3x, 30 px marked a lace of the board's inside)."""
    rng = np.random.default_rng(5)
    size = (640, 480)
    corners = rng.uniform([300.0, 200.0], [620.0, 470.0], (40, 2))  # one side and the bottom, as rig640's right
    u, v, _ = cd.grid_pixels(size, cd.GRID)
    f = cd.corner_field(u, v, corners)
    big = tuple(int(round(scale * s)) for s in size)
    ub, vb, _ = cd.grid_pixels(big, cd.GRID)
    # grid_pixels spans 0..w-1: the same grid pixel at the larger size sits at scale * (p + 0.5) - 0.5 relative to it
    fb = cd.corner_field(ub, vb, (corners + 0.5) * np.array(big) / np.array(size) - 0.5)
    assert 0.2 < f.mean() < 0.8
    assert (f != fb).mean() <= 0.01, (f.mean(), fb.mean(), (f != fb).sum())


def test_the_statistic_is_taken_inside_the_field_and_the_outside_read_apart(calibrated):
    """With a field, the ratio and the Mahalanobis median are those of the field's pixels alone: the difference
    planted 10x outside the field leaves them unchanged to rounding (the prediction and the weights do not move),
    and the pooled ratio outside grows 10x exactly while inside stays; the field over the whole grid is the
    statistic without one. The pooled ratios are sqrt(sum w |e|^2 / sum w trace C) by definition, checked by hand."""
    b = _perturbed(calibrated, 0.5 * np.sqrt(np.diag(calibrated.cov)))
    whole = cd.projection_diff(calibrated, b, 1000.0, GRID, SIZE)
    field = np.zeros((GRID[1], GRID[0]), bool)
    field[2:7, 3:10] = True
    d = cd.projection_diff(calibrated, b, 1000.0, GRID, SIZE, field=field)
    same = cd.projection_diff(calibrated, b, 1000.0, GRID, SIZE, field=np.ones_like(field))
    assert same.ratio == pytest.approx(whole.ratio, rel=1e-12) and d.ratio != pytest.approx(whole.ratio, rel=1e-3)
    m = d.ok & field
    w, e2, tr = d.weight[m], np.sum(d.diff[m] ** 2, axis=-1), np.trace(d.cov[m], axis1=-2, axis2=-1)
    assert d.ratio_raw == pytest.approx(np.sqrt(np.sum(w * e2) / np.sum(w * tr)), rel=1e-12)
    assert d.mahalanobis_median == pytest.approx(np.median(d.mahalanobis[m]), rel=1e-12)
    f0 = d.field_figures()
    planted = dataclasses.replace(d, diff=np.where(field[..., None], d.diff, 10.0 * d.diff), bands={})
    f1 = planted.field_figures()
    assert f1["ratio_pooled_inside"] == pytest.approx(f0["ratio_pooled_inside"], rel=1e-12)
    assert f1["ratio_pooled_outside"] == pytest.approx(10.0 * f0["ratio_pooled_outside"], rel=1e-12)
    assert planted.mahalanobis_median == pytest.approx(d.mahalanobis_median, rel=1e-12)
    lo, hi = f0["outside_over_inside_band_if_right"]
    assert lo < 1.0 < hi < f1["outside_over_inside"]


def test_the_simulated_statistic_over_the_field_is_the_observed_one_to_first_order(calibrated):
    """`simulate` (what every band draws) against the observed statistic: camera B = A moved by a small parameter
    step delta (1e-3 of each std: second-order terms ~1e-3 relative) has the difference F_B delta after the fit, so
    simulating the lens errors (0, delta) must give B's observed ratio and Mahalanobis median over the field's pixels,
    and the pooled numerators inside and outside; 1e-2 relative leaves 10x the second-order room."""
    rng = np.random.default_rng(5)
    delta = 1e-3 * np.sqrt(np.diag(calibrated.cov)) * rng.choice([-1.0, 1.0], len(calibrated.cov))
    field = np.zeros((GRID[1], GRID[0]), bool)
    field[1:6, 2:8] = True
    d = cd.projection_diff(calibrated, _perturbed(calibrated, delta), 1000.0, GRID, SIZE, field=field)
    ratio, maha, (n_in, n_out) = d.simulate(np.zeros((1, len(delta))), delta[None], pooled=True)
    assert ratio[0] == pytest.approx(d.ratio, rel=1e-2) and maha[0] == pytest.approx(d.mahalanobis_median, rel=1e-2)
    assert n_in[0] == pytest.approx(d.pooled(field)[0], rel=1e-2)
    assert n_out[0] == pytest.approx(d.pooled(~field)[0], rel=1e-2)


def test_fields_that_share_no_pixel_are_refused_with_what_to_do(calibrated):
    """Two calibrations whose corners' fields share no grid pixel leave the statistic nothing to be taken over: one
    refusal naming what to do (views that overlap, or --grid), not a ratio of no pixels."""
    from dstereo.errors import DstereoError

    with pytest.raises(DstereoError, match="no valid grid pixel.*--grid"):
        cd.projection_diff(calibrated, calibrated, 600.0, GRID, field=np.zeros((GRID[1], GRID[0]), bool))
