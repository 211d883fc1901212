"""The part of the rate's error common to all frames: each grid cell's own rate error, seen in the scatter of the
per-cell rates over the stagnation disc (issue 32).

Why the frames' scatter misses it. The stagnation value of frame i is a fixed linear combination of the cell
values, sum_c g_c r_c(t_i) (`fits.at_stagnation`: the intercept of a least-squares quadratic over the disc, or the
mean), so the rate is the same combination of the per-cell rates, sum_c g_c k_c (exactly, where every disc cell
has a value in every frame). A cell's rate is off by a_c + n_c: n_c from the frames' noise, and a_c from a
matching error that changes with the recession in the same way in every frame (the texture, and where it lies on
the pixel grid, are the cell's own: on a tilted face the disparity sweeps across the pixel grid as the face
recedes). The line through the stagnation values sees n_c, and the part of a_c that is not linear in time; a
linear a_c moves the rate and leaves no residual. Over the cells, though, the a_c scatter: the rates of the disc's
cells about the quadratic show a_c + n_c, and the rate's error from them is

    Var(sum_c g_c (a_c + n_c)) = s^2 g' P g,    P_cd = correlation of cells c and d

with s^2 the cells' variance and P their correlation at each offset (dx, dy) up to MAX_LAG cells (zero beyond),
both from the cells' residuals about the quadratic over a disc CORRELATION_DISC times the stagnation disc's radius
(more pairs than the disc alone, where a few dozen cells gave correlations that scattered by +-0.4), corrected for
what the fit absorbs (`_covariance_terms`). On maps with a per-cell rate error of 3 % (Gaussian-filtered noise,
sigma 0.8 cells; tests/recession/test_common_part.py, 120 draws) the residuals' raw mean products gave an interval
that covered 91 % with error / standard error of RMS 1.19; with the correction 96 % and 1.00 (a field correlated
over 1.5 cells, longer than MAX_LAG: 79 % and 1.46 raw, 92 % and 1.20 corrected).
The estimate is kept at least the independent-cell value s^2 g'g: neighbouring cells share the matching window and
the refinement's kernel, so their errors correlate positively, and an estimate below that is chance.

Only a_c is added to the frames' interval: n_c is in it already (the stagnation value's residuals about the line
are sum_c g_c times the cells' own). Each cell's line fit measures its n_c by its residuals over the frames
(`fits.rate_map`'s rate_se, unbiased for Var(n_c)), so a_c's share of s^2 is 1 - mean(rate_se^2) / s^2 (at least
0); the common part is that share of s^2 g'Pg. On renders with sensor noise the share was ~0 (the cells' scatter
is their frames' noise); a texture-bound error linear in time makes it large (tests/recession/test_common_part.py).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

MAX_LAG = 2  # cells: offsets with |dx|, |dy| <= MAX_LAG carry a correlation. Measured on the rate map of a
# 320 x 240 render (yaw 12 deg, seed 3) against its truth: 0.23 / 0.37 one cell apart in u / v, 0.14 / 0.16 two
# cells apart, -0.05..0.11 from three on
CORRELATION_DISC = 2.0  # the correlations come from the cells within this many stagnation radii


@dataclass(frozen=True)
class CellScatter:
    """The stagnation rate's error common to all frames (mm/s, a standard error) and its degrees of freedom; the
    cells' residual RMS about the quadratic (mm/s), the RMS of their own rates' standard errors over the frames
    (mm/s), the share of the cells' variance that is theirs alone (a_c), the cell count, and the variance factor
    g'Pg / g'g of their correlation."""

    se: float
    dof: float
    residual_rms: float
    frames_rms: float
    share: float
    cells: int
    inflation: float

    def as_dict(self) -> dict:
        return asdict(self)


def _design(u: np.ndarray, v: np.ndarray, quadratic: bool) -> np.ndarray:
    cols = [np.ones_like(u)] + ([u, v, u * u + v * v] if quadratic else [])
    return np.stack(cols, axis=1)


def _offsets() -> list[tuple[int, int]]:
    """(0, 0), then one of each +- pair of cell offsets with |dx|, |dy| <= MAX_LAG."""
    return [(0, 0)] + [(dx, dy) for dy in range(MAX_LAG + 1) for dx in range(-MAX_LAG, MAX_LAG + 1)
                       if dy > 0 or dx > 0]


def _pattern(ix: np.ndarray, iy: np.ndarray, offset: tuple[int, int]) -> np.ndarray:
    """(n, n) 0/1: the pairs of cells (ix, iy) at `offset` either way (the identity for (0, 0))."""
    ddx, ddy = ix[:, None] - ix[None, :], iy[:, None] - iy[None, :]
    dx, dy = offset
    return (((ddx == dx) & (ddy == dy)) | ((ddx == -dx) & (ddy == -dy))).astype(float)


def _covariance_terms(values, u, v, inside, spacing, quadratic) -> tuple[np.ndarray, list]:
    """theta_k, the cells' covariance at each of `_offsets()` (mm^2/s^2), from the residuals about the quadratic
    fitted over `inside`. A least-squares fit absorbs part of any error that is smooth over the cells, so the
    residuals' products understate the covariance; their expectations are linear in theta, E[e' E_k e] =
    sum_l theta_l tr(E_k M E_l M) with M = I - H the fit's residual projector and E_k the offset's pattern,
    and that system is solved for theta (moment matching, as REML does for a variance)."""
    q, _ = np.linalg.qr(_design(u[inside], v[inside], quadratic))  # the fit's hat matrix H = q q'
    z = values[inside]
    e = z - q @ (q.T @ z)
    ix, iy = np.round(u[inside] / spacing).astype(np.int64), np.round(v[inside] / spacing).astype(np.int64)
    patterns = [_pattern(ix, iy, o) for o in _offsets()]
    # tr(E_k M E_l M) = tr(E_k E_l) - 2 tr((E_k q)'(E_l q)) + tr((q'E_k q)(q'E_l q)) (H of rank p: no n x n
    # products); distinct offsets' patterns share no pair, so tr(E_k E_l) is the pair count on the diagonal
    eq = [pat @ q for pat in patterns]
    qeq = [q.T @ b for b in eq]
    gram = np.array([[float(np.sum(patterns[k] * patterns[k])) * (k == l) - 2.0 * float(np.sum(eq[k] * eq[l]))
                      + float(np.sum(qeq[k] * qeq[l].T)) for l in range(len(patterns))] for k in range(len(patterns))])
    stats = np.array([e @ (pat @ e) for pat in patterns])
    keep = [0] + [k for k in range(1, len(patterns)) if patterns[k].any()]
    theta = np.zeros(len(patterns))
    theta[keep] = np.linalg.lstsq(gram[np.ix_(keep, keep)], stats[keep], rcond=None)[0]
    return theta, _offsets()


def cell_scatter(values: np.ndarray, values_se: np.ndarray, u: np.ndarray, v: np.ndarray, radius: float,
                 spacing: float, model: str = "quadratic") -> CellScatter | None:
    """The stagnation rate's error common to all frames from the scatter of the per-cell rates `values` (mm/s)
    with their standard errors over the frames `values_se`, over the disc of `radius` (mm), cells of `spacing` mm
    at (u, v) (module docstring); the same estimator as `fits.at_stagnation` (quadratic from 12 cells on, else
    the mean). None with fewer than p + 2 cells in the disc."""
    finite = np.isfinite(values) & np.isfinite(values_se)
    disc = (u * u + v * v <= radius * radius) & finite
    n = int(disc.sum())
    quadratic = model == "quadratic" and n >= 12
    p = 4 if quadratic else 1
    if n < p + 2:
        return None
    region = (u * u + v * v <= (CORRELATION_DISC * radius) ** 2) & finite
    theta, offsets = _covariance_terms(values, u, v, region, spacing, quadratic)
    a = _design(u[disc], v[disc], quadratic)
    g = np.linalg.pinv(a)[0]  # the intercept as a combination of the disc cells' values
    res = values[disc] - a @ (np.linalg.pinv(a) @ values[disc])
    variance = theta[0] if theta[0] > 0 else float(res @ res) / (n - p)
    ix, iy = np.round(u[disc] / spacing).astype(np.int64), np.round(v[disc] / spacing).astype(np.int64)
    cov = sum(t * _pattern(ix, iy, o) for t, o in zip(theta[1:], offsets[1:])) + variance * np.eye(n)
    independent = variance * float(g @ g)
    inflation = max(float(g @ cov @ g) / independent, 1.0)
    frames2 = float(np.mean(values_se[region] ** 2))
    share = max(0.0, 1.0 - frames2 / variance)
    # Degrees of freedom: the region's residual dof over the variance factor (cells' worth of information)
    dof = max((int(region.sum()) - p) / inflation, 1.0)
    return CellScatter(float(np.sqrt(share * independent * inflation)), dof, float(np.sqrt(variance)),
                       float(np.sqrt(frames2)), share, n, inflation)
