"""Least-squares pieces of the recession analysis: the value at the stagnation point, and rates with their
95 % confidence intervals (the thesis's HSC analysis, 3.2.1: recession rate = slope of a line fitted over time).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from dstereo.errors import DstereoError


def _t_quantile(q, dof):
    """Student's t quantile. scipy.stats is imported here, not with the module: it takes ~1 s, and a frame's
    worker process imports this room without ever fitting a line."""
    from scipy import stats

    return stats.t.ppf(q, dof)

STAGNATION_MODELS = ("quadratic", "mean")


@dataclass(frozen=True)
class PointValue:
    """A value at the stagnation point (mm) with its standard error and the number of cells behind it."""

    value: float
    se: float
    cells: int


def at_stagnation(values: np.ndarray, u: np.ndarray, v: np.ndarray, radius: float, model: str = "quadratic",
                  min_cells: int = 4) -> PointValue:
    """Value at (u, v) = (0, 0) from the grid cells within `radius` (mm).

    `quadratic`: least squares a + b u + c v + d (u^2 + v^2), value a. The stagnation point is where a
    symmetric profile peaks, so a plain mean over the disc is biased by the curvature (a Gaussian peak of width
    sigma loses ~R^2/(4 sigma^2) of itself over a disc of radius R); the quadratic removes that at twice the
    standard error. Falls back to the mean when too few cells support the quadratic. `mean`: the disc mean.
    Standard errors treat cells as independent (neighbouring cells share SGBM's matching window, so they
    are a lower bound); the rate's confidence interval does not rely on them.
    """
    if model not in STAGNATION_MODELS:
        raise DstereoError(f"stagnation model {model!r}: use one of {', '.join(STAGNATION_MODELS)}")
    inside = (u * u + v * v <= radius * radius) & np.isfinite(values)
    n = int(inside.sum())
    if n < min_cells:
        return PointValue(float("nan"), float("nan"), n)
    x, y, z = u[inside], v[inside], values[inside]
    if model == "quadratic" and n >= 12:
        a = np.stack([np.ones(n), x, y, x * x + y * y], axis=1)
        coef, *_ = np.linalg.lstsq(a, z, rcond=None)
        res = z - a @ coef
        cov = np.linalg.pinv(a.T @ a) * (res @ res) / (n - 4)
        return PointValue(float(coef[0]), float(np.sqrt(cov[0, 0])), n)
    return PointValue(float(z.mean()), float(z.std(ddof=1) / np.sqrt(n)), n)


@dataclass(frozen=True)
class LineFit:
    """r = intercept + rate t by least squares; `ci95` the 95 % interval of the rate (Student t, n - 2 dof).
    With a part common to all frames (`with_common_part`): `rate_se` and `ci95` hold both parts, `dof` their
    Welch-Satterthwaite degrees of freedom, `rate_se_frames` / `ci95_frames` the frames' scatter alone and
    `rate_se_common` the common part."""

    rate: float
    rate_se: float
    ci95: tuple[float, float]
    intercept: float
    intercept_se: float
    residual_rms: float
    n: int
    weighted: bool = False
    rate_se_frames: float | None = None
    ci95_frames: tuple[float, float] | None = None
    rate_se_common: float | None = None
    dof: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def line_fit(t: np.ndarray, r: np.ndarray, sigma: np.ndarray | None = None) -> LineFit:
    """Straight line through (t, r). With `sigma` the points are weighted by 1/sigma^2 and the scale comes from
    the weighted residuals (so only relative sigmas matter). At least 3 points for an interval."""
    t, r = np.asarray(t, float), np.asarray(r, float)
    n = len(t)
    if n < 2:
        raise DstereoError(f"a rate needs at least 2 frames with a value; {n} left")
    w = np.ones(n) if sigma is None else 1.0 / np.asarray(sigma, float) ** 2
    a = np.stack([np.ones(n), t], axis=1)
    aw = a * w[:, None]
    cov_unit = np.linalg.inv(a.T @ aw)
    coef = cov_unit @ (aw.T @ r)
    res = r - a @ coef
    if n > 2:
        s2 = float(w @ res**2) / (n - 2)
        se = np.sqrt(np.diag(cov_unit) * s2)
        half = _t_quantile(0.975, n - 2) * se[1]
    else:
        se, half = np.full(2, np.nan), float("nan")
    return LineFit(float(coef[1]), float(se[1]), (float(coef[1] - half), float(coef[1] + half)), float(coef[0]),
                   float(se[0]), float(np.sqrt(np.mean(res**2))), n, sigma is not None)


def rate_map(t: np.ndarray, maps: np.ndarray, min_frames: int = 3) -> dict[str, np.ndarray]:
    """Per grid cell line fit of recession (frames, ny, nx) against t over the frames where the cell has a value:
    rate, its standard error, 95 % interval half-width (mm/s) and the frame count; NaN below `min_frames`."""
    t = np.asarray(t, float)[:, None, None]
    ok = np.isfinite(maps)
    n = ok.sum(axis=0)
    tt = np.where(ok, t, 0.0)
    rr = np.where(ok, maps, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        tm, rm = tt.sum(0) / n, rr.sum(0) / n
        dt = np.where(ok, t - tm, 0.0)
        sxx = (dt * dt).sum(0)
        rate = (dt * np.where(ok, maps - rm, 0.0)).sum(0) / sxx
        res = np.where(ok, maps - rm - rate * (t - tm), 0.0)
        s2 = (res * res).sum(0) / (n - 2)
        se = np.sqrt(s2 / sxx)
        half = _t_quantile(0.975, np.maximum(n - 2, 1)) * se
    few = n < min_frames
    return {"rate": np.where(few, np.nan, rate), "rate_se": np.where(few, np.nan, se),
            "ci95_half": np.where(few, np.nan, half), "frames": n.astype(int)}


def line_band(fit: LineFit, t: np.ndarray, r: np.ndarray, at: np.ndarray) -> np.ndarray | None:
    """Half-width of the 95 % confidence band of the fitted line at times `at` (unweighted residual scatter of
    the frames `t`, `r` the fit used); None with two frames or fewer, where the scatter is not estimable."""
    if fit.n <= 2:
        return None
    resid = r - (fit.intercept + fit.rate * t)
    s = np.sqrt(resid @ resid / (fit.n - 2))
    sxx = ((t - t.mean()) ** 2).sum()
    return _t_quantile(0.975, fit.n - 2) * s * np.sqrt(1 / fit.n + (at - t.mean()) ** 2 / sxx)


def with_common_part(fit: LineFit, common_se: float, common_dof: float) -> LineFit:
    """`fit` with an error common to all frames added to its rate's interval: the two are independent (one is the
    frames' scatter about the line, the other fixed over the frames), so their variances add, and the interval's
    t quantile takes the Welch-Satterthwaite degrees of freedom of the sum,
    (s_f^2 + s_c^2)^2 / (s_f^4 / (n - 2) + s_c^4 / dof_c). Without an interval (two frames) `fit` is returned."""
    if not np.isfinite(fit.rate_se) or fit.n <= 2:
        return fit
    total = float(np.hypot(fit.rate_se, common_se))
    parts = fit.rate_se**4 / (fit.n - 2) + (common_se**4 / common_dof if common_se > 0 else 0.0)
    dof = total**4 / parts if parts > 0 else float(fit.n - 2)
    half = float(_t_quantile(0.975, dof)) * total
    return replace(fit, rate_se=total, ci95=(fit.rate - half, fit.rate + half), rate_se_frames=fit.rate_se,
                   ci95_frames=fit.ci95, rate_se_common=float(common_se), dof=float(dof))
