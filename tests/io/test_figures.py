"""Figures a user can read: the helpers that choose scales, ticks, patches and statistics, checked against
independent computations, and a few drawn figures inspected (colour bars, labels, patches) before saving."""

import numpy as np
import pytest
from matplotlib import cbook
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from scipy.stats import gaussian_kde

from dstereo.calib.coverage import CORNER_MIN_PERCENT, corner_coverage
from dstereo.io import plots
from dstereo.io.figures import colour_limits, log_ticks, tick_label
from dstereo.io.plots import MAX_FLIERS, binned_kde, box_stats, corner_patches
from dstereo.io.sigma_maps import projection_uncertainty_png
from dstereo.io.rig_figures import frustum_depth
from dstereo.uncertainty.projection import ProjectionUncertaintyMap


@pytest.fixture
def saved(monkeypatch):
    """Figures as they were when saved (the functions close them right after)."""
    figures = []
    original = Figure.savefig

    def keep(self, *args, **kwargs):
        figures.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures


def _smooth_map():
    u, v = np.linspace(0, 639, 33), np.linspace(0, 479, 25)
    uu, vv = np.meshgrid(u, v)
    return u, v, 0.05 + 0.3 * ((uu - 320) ** 2 + (vv - 240) ** 2) / 400 ** 2


def test_colour_limits_ignore_one_huge_value_and_non_finite():
    _, _, std = _smooth_map()
    lo, hi, extend = colour_limits(std)
    assert (lo, hi, extend) == (0.0, float(std.max()), "neither")  # a clean map keeps its full range
    bad = std.copy()
    bad[0, 0], bad[0, 1], bad[3, 3] = 4e13, np.nan, np.inf
    lo, hi, extend = colour_limits(bad)
    finite = bad[np.isfinite(bad)]
    assert extend == "max" and hi == pytest.approx(np.percentile(finite, 99))
    assert hi <= std.max()  # the scale shows the bulk, not the outlier
    signed = np.concatenate([np.linspace(-1, 1, 500), [-1e6, 1e9]])
    lo, hi, extend = colour_limits(signed, 99, lower=1)
    assert extend == "both" and -1 <= lo < 0 < hi <= 1


def test_projection_map_with_an_outlier_is_scaled_to_the_bulk(tmp_path, saved):
    u, v, std = _smooth_map()
    std[0, 0], std[0, 1] = 4e13, np.nan
    pmap = ProjectionUncertaintyMap(u, v, np.zeros(std.shape + (2, 2)), std, 600.0)
    projection_uncertainty_png(tmp_path / "p.png", pmap, (640, 480), "test", "mm")
    image = saved[0].axes[0].get_images()[0]
    assert image.norm.vmax <= np.nanmax(np.where(std < 1e3, std, np.nan))
    assert (tmp_path / "p.png").stat().st_size > 0 and len(saved[0].axes) == 2  # map + colour bar


def test_coverage_patches_are_the_regions_counted_and_drawn(tmp_path, saved):
    rng = np.random.default_rng(0)
    points = rng.uniform([200, 60], [600, 470], (1500, 2))  # nothing in the two left image corners
    cov = corner_coverage(points, (640, 480))
    for name, (x0, y0, w, h) in corner_patches((640, 480)).items():
        inside = (points[:, 0] >= x0) & (points[:, 0] < x0 + w) & (points[:, 1] >= y0) & (points[:, 1] < y0 + h)
        assert 100 * inside.mean() == pytest.approx(cov.corner_percent[name], abs=1e-9), name
    plots.coverage_heatmap(points, (640, 480), cov.percent, tmp_path / "c.png", cov.corner_percent,
                           CORNER_MIN_PERCENT)
    warned = sum("image corner" in w for w in cov.warnings)
    orange = [p for p in saved[0].axes[0].patches if p.get_edgecolor() == to_rgba("tab:orange")]
    assert warned == 2 and len(orange) == warned


def test_residuals_have_a_colour_bar_and_axis_labels(tmp_path, saved):
    rng = np.random.default_rng(1)
    observed = rng.uniform(0, 600, (4, 54, 2))
    plots.residual_vectors(observed, rng.normal(0, 0.1, observed.shape), (640, 480), tmp_path / "r.png")
    main, bar = saved[0].axes
    assert main.get_xlabel() == "x (px)" and main.get_ylabel() == "y (px)" and "px" in bar.get_ylabel()


@pytest.mark.parametrize("lo,hi", [(0.31, 250.0), (0.05, 0.09), (2.0, 3.0), (8.0, 2.4e4)])
def test_log_ticks_are_distinct_inside_and_never_zero(lo, hi):
    ticks = log_ticks(lo, hi)
    labels = [tick_label(t) for t in ticks]
    assert len(ticks) >= 3 and (ticks >= lo).all() and (ticks <= hi).all()
    assert len(set(labels)) == len(labels) and all(float(s) > 0 for s in labels)


def test_frustum_scaled_to_the_baseline():
    assert frustum_depth(110.0, 600.0) == 55.0  # half the baseline: two frusta stay apart
    assert frustum_depth(1000.0, 600.0) == 150.0 and frustum_depth(1.0, 600.0) == 18.0  # 25 % / 3 % of distance


def test_box_stats_are_matplotlibs():
    x = np.random.default_rng(2).standard_t(1, 20001)  # Cauchy: ~15 % fliers
    ours, ref = box_stats(x), cbook.boxplot_stats(x)[0]
    for key in ("med", "q1", "q3", "whislo", "whishi", "mean"):
        assert ours[key] == pytest.approx(ref[key], rel=1e-12, abs=1e-12), key  # same formulas, float64 rounding
    assert len(ref["fliers"]) > MAX_FLIERS >= len(ours["fliers"])
    assert ours["fliers"].min() == ref["fliers"].min() and ours["fliers"].max() == ref["fliers"].max()


def test_binned_kde_matches_scipy():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(800, 0.5, 20000), rng.normal(803, 0.2, 3000), [850.0]])
    grid = np.linspace(x.min(), x.max(), 400)
    exact = gaussian_kde(x)(grid)
    # Linear binning at spacing <= h / 10: error below (1/10)^2 / 8 of the peak (binned_kde's docstring).
    assert np.max(np.abs(binned_kde(x, grid) - exact)) <= 1.25e-3 * exact.max()


def test_parameter_figure_of_a_million_subsets_draws_summaries(tmp_path, saved):
    x = np.random.default_rng(4).normal(800, 0.3, 10 ** 6)
    plots.parameter_figure("fx", x, x[np.abs(x - 800) < 0.6], tmp_path / "fx.png", "px", 800.0)
    hist, box = saved[0].axes
    assert sum(len(line.get_xdata()) for line in box.get_lines()) < 5000
    # each set's KDE drawn over its histogram in subsets per bin: its area equals the bars' (the set's size)
    curves = [line for line in hist.get_lines() if len(line.get_xdata()) == 400]
    assert len(curves) == 2 and len(hist.patches) == 2
    for curve, size in zip(curves, (x.size, int(np.sum(np.abs(x - 800) < 0.6)))):
        gx, gy = curve.get_xdata(), curve.get_ydata()
        width = (gx[-1] - gx[0]) / 30  # 30 bins over the grid's span
        assert np.trapezoid(gy, gx) / width == pytest.approx(size, rel=0.02)  # mass beyond the grid's ends: < 2 %
    assert hist.get_ylabel() == "subsets per bin"


def test_wide_angle_map_gets_a_log_scale(tmp_path, saved):
    # A rational model on a fisheye: ~0.4 px in the middle, tens of px towards the rim, 1e3+ px spikes there.
    u, v, std = _smooth_map()
    wide = 0.4 * np.exp(25 * (std - 0.05))
    wide[0, :3] = [1.5e3, np.nan, 4e13]
    pmap = ProjectionUncertaintyMap(u, v, np.zeros(wide.shape + (2, 2)), wide, 100.0)
    projection_uncertainty_png(tmp_path / "w.png", pmap, (640, 480), "test", "mm")
    norm = saved[0].axes[0].get_images()[0].norm
    assert type(norm).__name__ == "LogNorm" and norm.vmin == pytest.approx(np.nanmin(wide))
    assert norm.vmax == pytest.approx(np.percentile(wide[np.isfinite(wide)], 99))
